"""ControlAPI: every command in every state, and its reply codes (at-most-once transaction ids:
tests/service/core/commands/test_transactions.py)."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from ride_machine.schema.commands import ALLOWED_STATES, CheckResult, Command, ReplyCode
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MOTION_STATES, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.statemachine import (
    HANDLING,
    TABLE,
    Occurrence,
    allowed_states,
    edges,
)
from tests.rig import BAD_SESSION, Rig, known_calibration, rig_in

S = MachineState
C = Command
E = ErrorCode
R = ReplyCode

RELEASED = "FAULT_ESTOP_RELEASED"
"""FAULT_ESTOP after the E-stop was released again (latched, input clear)."""


@dataclass(frozen=True)
class Ok:
    code: ReplyCode
    state: MachineState


@dataclass(frozen=True)
class Refused:
    error: ErrorCode
    state: MachineState | None = None
    """The state afterwards when a refusal moves it (Start's warnings); None = unchanged."""


CAL = Ok(R.RESP_CALIBRATION_ACCEPTED, S.CALIBRATING)
HOME = Ok(R.RESP_HOME_ACCEPTED, S.HOMING)
START = Ok(R.RESP_START_ACCEPTED, S.RUNNING)
PAUSE = Ok(R.RESP_PAUSED, S.PAUSED)
STOP = Ok(R.RESP_DONE, S.DONE)
WRONG = Refused(E.WRONG_STATE)
ESTOP = Refused(E.ESTOP_ACTIVE)


def check(state: MachineState) -> Ok:
    return Ok(R.RESP_CHECK, state)


# The specification, written out by hand (not derived from the code under test). Rig recipes in
# tests/rig.py: FAULT_ESTOP was pressed while IDLE, FAULT_HW comes from an invalid session, DONE
# is a finished default session (tilt left at 45°, rotate on its home switch).
EXPECTED: dict[str, dict[Command, Ok | Refused]] = {
    S.IDLE: {
        C.CALIBRATE_TILT: CAL,
        C.CALIBRATE_ROTATE: CAL,
        C.HOME: HOME,
        C.START: START,
        C.PAUSE: WRONG,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.IDLE),
        C.CHECK_HOME: check(S.IDLE),
    },
    S.HOMING: {
        C.CALIBRATE_TILT: WRONG,
        C.CALIBRATE_ROTATE: WRONG,
        C.HOME: WRONG,
        C.START: WRONG,
        C.PAUSE: PAUSE,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.HOMING),
        C.CHECK_HOME: check(S.HOMING),
    },
    S.CALIBRATING: {
        C.CALIBRATE_TILT: WRONG,
        C.CALIBRATE_ROTATE: WRONG,
        C.HOME: WRONG,
        C.START: WRONG,
        C.PAUSE: PAUSE,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.CALIBRATING),
        C.CHECK_HOME: check(S.CALIBRATING),
    },
    S.RUNNING: {
        C.CALIBRATE_TILT: WRONG,
        C.CALIBRATE_ROTATE: WRONG,
        C.HOME: WRONG,
        C.START: WRONG,
        C.PAUSE: PAUSE,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.RUNNING),
        C.CHECK_HOME: check(S.RUNNING),
    },
    S.PAUSED: {
        C.CALIBRATE_TILT: WRONG,
        C.CALIBRATE_ROTATE: WRONG,
        C.HOME: WRONG,
        C.START: WRONG,
        C.PAUSE: WRONG,
        C.RESUME: Ok(R.RESP_RESUMED, S.RUNNING),
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.PAUSED),
        C.CHECK_HOME: check(S.PAUSED),
    },
    S.DONE: {
        C.CALIBRATE_TILT: CAL,
        C.CALIBRATE_ROTATE: CAL,
        C.HOME: HOME,
        C.START: Refused(E.NOT_HOME, S.WARNING_NOT_HOME),
        C.PAUSE: WRONG,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.DONE),
        C.CHECK_HOME: check(S.WARNING_NOT_HOME),
    },
    S.FAULT_ESTOP: {
        C.CALIBRATE_TILT: ESTOP,
        C.CALIBRATE_ROTATE: ESTOP,
        C.HOME: ESTOP,
        C.START: ESTOP,
        C.PAUSE: ESTOP,
        C.RESUME: ESTOP,
        C.STOP: ESTOP,
        C.CHECK_CALIBRATION: check(S.FAULT_ESTOP),
        C.CHECK_HOME: check(S.FAULT_ESTOP),
    },
    RELEASED: {
        C.CALIBRATE_TILT: WRONG,
        C.CALIBRATE_ROTATE: WRONG,
        C.HOME: HOME,
        C.START: WRONG,
        C.PAUSE: WRONG,
        C.RESUME: Ok(R.RESP_RESUMED, S.IDLE),
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.FAULT_ESTOP),
        C.CHECK_HOME: check(S.FAULT_ESTOP),
    },
    S.FAULT_HW: {
        C.CALIBRATE_TILT: CAL,
        C.CALIBRATE_ROTATE: CAL,
        C.HOME: HOME,
        C.START: WRONG,
        C.PAUSE: WRONG,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.FAULT_HW),
        C.CHECK_HOME: check(S.FAULT_HW),
    },
    S.WARNING_NEEDS_CALIBRATION: {
        C.CALIBRATE_TILT: CAL,
        C.CALIBRATE_ROTATE: CAL,
        C.HOME: HOME,
        C.START: Refused(E.NOT_CALIBRATED, S.WARNING_NEEDS_CALIBRATION),
        C.PAUSE: WRONG,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.WARNING_NEEDS_CALIBRATION),
        # Not home either, but the calibration warning is the bigger one and stays.
        C.CHECK_HOME: check(S.WARNING_NEEDS_CALIBRATION),
    },
    S.WARNING_NOT_HOME: {
        C.CALIBRATE_TILT: CAL,
        C.CALIBRATE_ROTATE: CAL,
        C.HOME: HOME,
        C.START: Refused(E.NOT_HOME, S.WARNING_NOT_HOME),
        C.PAUSE: WRONG,
        C.RESUME: WRONG,
        C.STOP: STOP,
        C.CHECK_CALIBRATION: check(S.WARNING_NOT_HOME),
        C.CHECK_HOME: check(S.WARNING_NOT_HOME),
    },
}

ALL = CheckResult(ok=True, tilt=True, rotate=True)
NONE = CheckResult(ok=False, tilt=False, rotate=False)
ROTATE_ONLY = CheckResult(ok=False, tilt=False, rotate=True)

# (CheckCalibration, CheckHome) results in each situation.
CHECKS: dict[str, tuple[CheckResult, CheckResult]] = {
    S.IDLE: (ALL, ALL),
    S.HOMING: (ALL, NONE),  # a reference exists only once homing has finished
    S.CALIBRATING: (NONE, NONE),
    S.RUNNING: (ALL, ROTATE_ONLY),  # tilting up, rotate still on its switch
    S.PAUSED: (ALL, ROTATE_ONLY),
    S.DONE: (ALL, ROTATE_ONLY),  # tilt left at 45°, rotate stopped on its switch
    S.FAULT_ESTOP: (ALL, ALL),
    RELEASED: (ALL, ALL),
    S.FAULT_HW: (ALL, NONE),  # a hardware fault drops the references until re-homed
    S.WARNING_NEEDS_CALIBRATION: (NONE, NONE),
    S.WARNING_NOT_HOME: (ALL, NONE),
}

CASES = [(situation, command) for situation in EXPECTED for command in Command]


def situation_rig(situation: str) -> Rig:
    if situation == RELEASED:
        return rig_in(S.FAULT_ESTOP, estop_held=False)
    return rig_in(S(situation))


def test_table_covers_every_state_and_command() -> None:
    assert {s for s in EXPECTED if s != RELEASED} == set(S)
    assert all(set(row) == set(Command) for row in EXPECTED.values())


@pytest.mark.parametrize("command", list(Command))
def test_allowed_state_table_matches_the_specification(command: Command) -> None:
    """With the E-stop released, a command is accepted in exactly the states the spec lists."""
    accepting = set()
    for situation, row in EXPECTED.items():
        if situation == S.FAULT_ESTOP:
            continue  # held: refused for the E-stop, not for the state
        state = S.FAULT_ESTOP if situation == RELEASED else S(situation)
        outcome = row[command]
        if isinstance(outcome, Ok) or outcome.error is not E.WRONG_STATE:
            accepting.add(state)
    assert accepting == set(allowed_states(command))


@pytest.mark.parametrize(("situation", "command"), CASES, ids=[f"{s}-{c}" for s, c in CASES])
def test_command_in_state(situation: str, command: Command) -> None:
    rig = situation_rig(situation)
    before = rig.state
    expected = EXPECTED[situation][command]

    reply = rig.send(command)

    assert reply.command == command.value
    assert reply.transaction_id == rig.replies[-1].transaction_id
    assert reply.timecode == rig.clock()
    if isinstance(expected, Ok):
        assert reply.success, reply.error
        assert reply.code is expected.code
        assert reply.error is None
        assert reply.error_message == ""
        assert rig.state is expected.state
    else:
        assert not reply.success
        assert reply.code is R.RESP_ERROR
        assert reply.error is not None
        assert reply.error.code is expected.error
        assert reply.error_message == reply.error.message
        assert command.value in reply.error.message
        if expected.error is E.WRONG_STATE:
            assert str(before) in reply.error.message
        assert rig.state is (expected.state or before)
    assert reply.state is rig.state
    assert rig.state is before or rig.state in table_targets(before, command)
    if command in (C.CHECK_CALIBRATION, C.CHECK_HOME):
        cal, home = CHECKS[situation]
        assert reply.result == (cal if command is C.CHECK_CALIBRATION else home)
    else:
        assert reply.result is None

    # Whatever the answer, the next cycle writes outputs that agree with the new state.
    rig.step()
    if rig.state not in MOTION_STATES:
        assert not rig.relays_on()


def table_targets(state: MachineState, trigger: Command | Occurrence) -> set[MachineState]:
    return {t for r in TABLE if r.trigger is trigger and state in r.sources for t in r.targets}


def test_transition_table_agrees_with_allowed_states() -> None:
    """The table's command rows accept exactly ALLOWED_STATES (the Rider's copy); every
    command has its handler, every event its rows."""
    assert set(HANDLING) == set(Command)
    for command in Command:
        rows = [r for r in TABLE if r.trigger is command]
        assert rows, command
        assert set().union(*(r.sources for r in rows)) == ALLOWED_STATES[command]
        assert allowed_states(command) == ALLOWED_STATES[command]
    assert {r.trigger for r in TABLE if isinstance(r.trigger, Occurrence)} == set(Occurrence)


def test_transitions_seen_on_a_whole_ride_are_in_the_table() -> None:
    rig = Rig()
    rig.calibrate()
    rig.home()
    rig.send(C.START)
    rig.run_to_state(S.DONE)
    seen = {(t.old, t.new) for t in rig.transitions}
    assert (S.HOMING, S.IDLE) in seen and (S.RUNNING, S.DONE) in seen
    assert seen <= edges()


def test_start_refusals_name_the_missing_axes() -> None:
    rig = Rig()
    reply = rig.send(C.START)
    assert reply.error is not None
    assert "tilt and rotate not calibrated" in reply.error.message

    rig = Rig(calibration=known_calibration())
    reply = rig.send(C.START)
    assert reply.error is not None
    assert reply.error.code is E.NOT_HOME
    assert "tilt and rotate not home" in reply.error.message


@pytest.mark.hazard("H29")
def test_start_with_invalid_session_is_refused_and_faults() -> None:
    rig = rig_in(S.IDLE)
    tilt = rig.hal.world.tilt_deg
    reply = rig.send(C.START, session=BAD_SESSION.model_dump())

    assert reply.error is not None
    assert reply.error.code is E.INVALID_SESSION
    assert reply.error.path == "/session/steps/0/degrees"
    assert "80" in reply.error.message
    assert rig.state is S.FAULT_HW
    assert rig.state_machine.fault is not None
    assert rig.state_machine.fault.code == "INVALID_SESSION"
    rig.step(100)
    assert not rig.relays_on()
    assert rig.hal.world.tilt_deg == tilt


@pytest.mark.hazard("H29")
def test_session_range_comes_from_the_machine_config() -> None:
    config = MachineConfig().with_overrides(tilt={"max_deg": 90.0})
    rig = Rig(config=config, calibration=known_calibration())
    rig.home()
    reply = rig.send(C.START, session=BAD_SESSION.model_dump())
    assert reply.success, reply.error
    assert rig.state is S.RUNNING


def test_stop_clears_the_session_and_fault() -> None:
    rig = rig_in(S.FAULT_HW)
    assert rig.state_machine.fault is not None
    assert rig.send(C.STOP).success
    assert rig.state_machine.fault is None
    assert rig.state_machine.context.drive.session_run is None

    rig = rig_in(S.RUNNING)
    assert rig.state_machine.context.drive.session_run is not None
    assert rig.send(C.STOP).success
    rig.step()
    assert rig.state_machine.context.drive.session_run is None
    assert rig.loop.published.status is not None
    assert rig.loop.published.status.session is None


def test_pause_then_resume_returns_to_homing_and_it_completes() -> None:
    rig = rig_in(S.HOMING)
    assert rig.send(C.PAUSE).success
    rig.step(200)
    assert rig.state is S.PAUSED
    assert not rig.relays_on()
    reply = rig.send(C.RESUME)
    assert reply.state is S.HOMING
    rig.run_to_state(S.IDLE, S.FAULT_HW)
    assert rig.state is S.IDLE


def test_passing_check_home_leaves_a_good_rest_state_alone() -> None:
    rig = rig_in(S.IDLE)
    assert rig.send(C.STOP).success  # DONE while still on both home switches
    assert rig.send(C.CHECK_HOME).result == CheckResult(ok=True, tilt=True, rotate=True)
    assert rig.state is S.DONE


def test_state_transitions_are_reported_with_a_reason() -> None:
    rig = rig_in(S.IDLE)
    rig.transitions.clear()
    rig.send(C.START)
    rig.run_to_state(S.DONE)
    assert [(t.old, t.new) for t in rig.transitions] == [(S.IDLE, S.RUNNING), (S.RUNNING, S.DONE)]
    assert rig.transitions[-1].reason == "session complete"
    assert all(t.at <= rig.clock() for t in rig.transitions)


# ---------------------------------------------------------------------------- transactions
