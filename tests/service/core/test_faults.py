"""Every injected fault ends in FAULT_HW, outputs safe, within the configured timeout."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import pytest

from ride_machine.hal.iomap import Signal
from ride_machine.schema.commands import Command
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.sim.physics import SwitchFault
from tests.rig import Rig, known_calibration

S = MachineState
C = Command
F = FaultCode

# Timeouts differ from the defaults, so the tests prove the configured values are the ones used.
CONFIG = MachineConfig().with_overrides(
    rotate={"revolution_timeout_s": 6.0, "backoff_timeout_s": 1.5},
    tilt={"home_timeout_s": 7.0, "follow_window_s": 0.4, "move_timeout_margin_s": 1.5},
)
PERIOD = CONFIG.loop.period_s
MARGIN = 3 * PERIOD
"""Detection happens on a cycle boundary: allow a few cycles beyond the timeout."""
TILT_MOVE_TIMEOUT = 1.5 * 45.0 / CONFIG.tilt.nominal_speed_dps + CONFIG.tilt.move_timeout_margin_s
NOISE_WINDOW_S = 1.0
"""TiltSupervisor counts jumps within one second."""
FOLLOW_S = 2 * CONFIG.tilt.follow_window_s
"""Following is judged per window: a fault that starts mid-window still shows the movement made
before it, so it is caught at the end of the next window, at most two windows later."""


def homing(rig: Rig) -> None:
    """Not home after power-up: Home from WARNING_NOT_HOME."""
    assert rig.send(C.HOME).success


def start(rig: Rig) -> None:
    assert rig.send(C.START).success


def nothing(rig: Rig) -> None:
    """The fault is there before the command that will meet it."""


def homing_rotate(rig: Rig) -> None:
    """Home, up to the moment the rotate axis is driven (tilt already home)."""
    homing(rig)
    rig.run_until(lambda: rig.hal.relay(Signal.ROTATE_RELAY))


def session_step(index: int) -> Callable[[Rig], None]:
    def setup(rig: Rig) -> None:
        rig.home()
        assert rig.send(C.START).success
        run = rig.state_machine.context.drive.session_run
        assert run is not None
        rig.run_until(lambda: run.index == index and rig.relays_on())
        rig.step(30)

    return setup


def calibrating(command: Command) -> Callable[[Rig], None]:
    def setup(rig: Rig) -> None:
        assert rig.send(command).success

    return setup


@dataclass(frozen=True)
class FaultCase:
    name: str
    setup: Callable[[Rig], None]
    inject: Callable[[Rig], None]
    codes: frozenset[FaultCode]
    timeout_s: float
    """The configured time within which the fault must be detected, from injection."""
    axis: str
    trigger: Callable[[Rig], None] = lambda rig: None
    """What sets the machine moving after the injection (a fault present before the command)."""


def stick(axis: str, fault: SwitchFault) -> Callable[[Rig], None]:
    return lambda rig: rig.hal.stick_home(axis, fault)


def stall(axis: str) -> Callable[[Rig], None]:
    return lambda rig: rig.hal.stall(axis)


def frozen(rig: Rig) -> None:
    rig.hal.freeze_tilt_ai()


def noisy(rig: Rig) -> None:
    rig.hal.set_tilt_noise(400)


REV = CONFIG.rotate.revolution_timeout_s
BACKOFF = CONFIG.rotate.backoff_timeout_s
TILT_HOME = CONFIG.tilt.home_timeout_s
STROKE = CONFIG.tilt.calibration_stroke_s
OPEN, CLOSED = SwitchFault.STUCK_OPEN, SwitchFault.STUCK_CLOSED
ROT_TIMEOUT = frozenset({F.ROTATE_HOME_TIMEOUT})
NOT_FOLLOWING = frozenset({F.TILT_NOT_FOLLOWING})
HOME_STUCK = frozenset({F.TILT_HOME_STUCK})
CASES = [
    FaultCase("rotate-home-open-homing", homing_rotate, stick("rotate", OPEN), ROT_TIMEOUT, REV,
              "rotate"),
    FaultCase("rotate-home-open-session", session_step(1), stick("rotate", OPEN), ROT_TIMEOUT,
              REV, "rotate"),
    # Stuck closed while seeking looks exactly like arriving home; stuck before Home is caught.
    FaultCase("rotate-home-closed-homing", nothing, stick("rotate", CLOSED), ROT_TIMEOUT, BACKOFF,
              "rotate", homing_rotate),
    # Mid-revolution a switch stuck closed is an edge far too early for the calibrated
    # revolution (RevolutionCheck): caught at once.
    FaultCase("rotate-home-closed-session", session_step(1), stick("rotate", CLOSED),
              frozenset({F.ROTATE_SPEED_IMPLAUSIBLE}), REV, "rotate"),
    FaultCase("tilt-home-open-homing", nothing, stick("tilt", OPEN),
              frozenset({F.TILT_HOME_TIMEOUT, F.TILT_NOT_FOLLOWING}), TILT_HOME, "tilt", homing),
    FaultCase("tilt-home-closed-session", Rig.home, stick("tilt", CLOSED), HOME_STUCK,
              TILT_MOVE_TIMEOUT, "tilt", start),
    FaultCase("tilt-home-closed-calibration", calibrating(C.CALIBRATE_TILT), stick("tilt", CLOSED),
              HOME_STUCK, STROKE + TILT_HOME, "tilt"),
    FaultCase("tilt-ai-frozen-session", session_step(0), frozen, NOT_FOLLOWING, FOLLOW_S, "tilt"),
    FaultCase("tilt-ai-frozen-homing", nothing, frozen, NOT_FOLLOWING, FOLLOW_S, "tilt", homing),
    FaultCase("tilt-ai-noisy-session", session_step(0), noisy, frozenset({F.TILT_SIGNAL_NOISY}),
              NOISE_WINDOW_S, "tilt"),
    FaultCase("rotate-drive-stalled-session", session_step(1), stall("rotate"), ROT_TIMEOUT, REV,
              "rotate"),
    FaultCase("rotate-drive-stalled-homing", homing_rotate, stall("rotate"), ROT_TIMEOUT, REV,
              "rotate"),
    FaultCase("tilt-drive-stalled-session", session_step(0), stall("tilt"), NOT_FOLLOWING,
              FOLLOW_S, "tilt"),
    FaultCase("tilt-drive-stalled-homing", nothing, stall("tilt"), NOT_FOLLOWING, FOLLOW_S, "tilt",
              homing),
]  # fmt: skip


@pytest.mark.hazard("H13", "H14", "H16", "H17", "H19")
@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_fault_ends_in_fault_hw_with_safe_outputs_within_timeout(case: FaultCase) -> None:
    calibration = None if case.name.endswith("calibration") else known_calibration()
    rig = Rig(config=CONFIG, calibration=calibration)
    case.setup(rig)
    moving = rig.state
    assert moving in (S.WARNING_NOT_HOME, S.IDLE, S.HOMING, S.RUNNING, S.CALIBRATING)

    case.inject(rig)
    case.trigger(rig)
    taken = rig.run_to_state(S.FAULT_HW, max_s=case.timeout_s + 10)  # from injection or command

    assert taken <= case.timeout_s + MARGIN
    assert not rig.relays_on()  # in the very cycle the fault was raised
    fault = rig.state_machine.fault
    assert fault is not None
    assert fault.code in case.codes
    assert fault.axis == case.axis
    assert fault.message
    status = rig.loop.published.status
    assert status is not None
    assert status.state == "FAULT_HW"
    assert status.fault == fault
    assert not status.homed.tilt
    assert not status.homed.rotate
    world = rig.hal.world
    where = (world.rotate_travel_deg, world.tilt_deg)
    for _ in range(500):
        rig.step()
        assert not rig.relays_on()
    assert rig.state is S.FAULT_HW
    assert (world.rotate_travel_deg, world.tilt_deg) == where


@pytest.mark.hazard("H16", "H17")
@pytest.mark.parametrize(
    ("timeout_s", "fault", "before_home"),
    [
        (CONFIG.rotate.revolution_timeout_s, SwitchFault.STUCK_OPEN, False),
        (CONFIG.rotate.backoff_timeout_s, SwitchFault.STUCK_CLOSED, True),
    ],
    ids=["seek", "backoff"],
)
def test_rotate_home_timeout_is_the_configured_one(
    timeout_s: float, fault: SwitchFault, before_home: bool
) -> None:
    """Not early either: a healthy but slow search must get its full configured time."""
    rig = Rig(config=CONFIG, calibration=known_calibration())
    if before_home:
        rig.hal.stick_home("rotate", fault)
    homing_rotate(rig)
    rig.hal.stick_home("rotate", fault)
    taken = rig.run_to_state(S.FAULT_HW, max_s=timeout_s + 5)
    assert timeout_s - MARGIN <= taken <= timeout_s + MARGIN


def test_recovery_after_a_fault_needs_home_and_then_runs_a_session() -> None:
    rig = Rig(config=CONFIG, calibration=known_calibration())
    session_step(1)(rig)
    rig.hal.stall("rotate")
    rig.run_to_state(S.FAULT_HW, max_s=REV + 1)
    refused = rig.send(C.START)
    assert refused.error is not None
    assert refused.error.code == "WRONG_STATE"

    rig.hal.clear_faults()
    rig.home()
    travel0 = rig.hal.world.rotate_travel_deg
    assert rig.send(C.START).success
    rig.run_to_state(S.DONE, S.FAULT_HW)
    assert rig.state is S.DONE, rig.state_machine.fault
    assert rig.state_machine.fault is None
    assert rig.hal.world.rotate_travel_deg - travel0 == pytest.approx(1080.0, abs=1.0)


@pytest.mark.hazard("H14", "H24")
def test_failed_tilt_calibration_keeps_the_previous_one() -> None:
    rig = Rig(config=CONFIG, calibration=known_calibration())
    before = rig.state_machine.calibration
    assert rig.send(C.CALIBRATE_TILT).success
    rig.run_until(lambda: rig.hal.relay(Signal.TILT_DIR))  # the measuring stroke (up) began
    rig.hal.freeze_tilt_ai()
    rig.run_to_state(S.FAULT_HW, max_s=CONFIG.tilt.calibration_stroke_s + 1)
    assert rig.state_machine.fault is not None
    assert rig.state_machine.fault.code in (F.TILT_NOT_FOLLOWING, F.CALIBRATION_IMPLAUSIBLE)
    assert rig.state_machine.calibration == before
    assert rig.machine.devices.tilt.calibration == before.tilt
    assert rig.memory is not None
    assert rig.memory.saved == []


def test_failed_rotate_calibration_stores_nothing() -> None:
    rig = Rig(config=CONFIG)
    rig.hal.stick_home("rotate", SwitchFault.STUCK_OPEN)
    assert rig.send(C.CALIBRATE_ROTATE).success
    rig.run_to_state(S.FAULT_HW, max_s=30)
    assert rig.state_machine.fault is not None
    assert rig.state_machine.fault.code is F.ROTATE_HOME_TIMEOUT
    assert rig.state_machine.calibration.rotate is None
    assert not rig.relays_on()


@pytest.mark.hazard("H19", "H24")
def test_rotate_speed_far_from_nominal_fails_calibration() -> None:
    config = CONFIG.with_overrides(hal={"sim": {"rotate_speed_dps": 200.0}})
    rig = Rig(config=config)
    assert rig.send(C.CALIBRATE_ROTATE).success
    rig.run_to_state(S.FAULT_HW, S.WARNING_NEEDS_CALIBRATION, max_s=60)
    assert rig.state is S.FAULT_HW
    assert rig.state_machine.fault is not None
    assert rig.state_machine.fault.code is F.CALIBRATION_IMPLAUSIBLE
    assert rig.state_machine.calibration.rotate is None


@pytest.mark.hazard("H13", "H24")
def test_inverted_tilt_wiring_fails_calibration() -> None:
    """An analog input that falls as the seat rises: the counts must rise going up (the
    commissioned gain is positive), so the first seek down stops within a follow window. Its
    values lie where a sound sensor's can (3000 down to 600 counts from 0 to 60°): one that
    reads where none can is TILT_SIGNAL_RANGE at rest (test_signal_range.py)."""
    config = CONFIG.with_overrides(
        hal={"sim": {"ai_gain_counts_per_deg": -40.0, "ai_offset_counts": 3000.0}}
    )
    rig = Rig(config=config)
    assert rig.send(C.CALIBRATE_TILT).success
    rig.run_until(lambda: rig.state is not S.CALIBRATING, max_s=60)
    assert rig.state is S.FAULT_HW
    assert rig.state_machine.fault is not None
    assert rig.state_machine.fault.code is F.TILT_NOT_FOLLOWING
    assert rig.state_machine.calibration.tilt is None
