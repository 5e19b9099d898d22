"""Homing and calibration on the fake clock (issue 37, docs/homing.md): a defined approach, the
edge latched from the scans either side of it, repeatability checked, plausibility while moving.
Each reproduction of the issue has its test here; tests/integration/test_homing.py runs them
through a real daemon."""

from __future__ import annotations

import tomllib
from collections.abc import Callable

import pytest

from ride_machine.schema.calibration import CalibrationSet, RotateCalibrationSet, TiltCalibrationSet
from ride_machine.schema.commands import Command, Direction, RotateStep, Session, StartRequest
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.calibrate import RotateCalibrate, TiltCalibrate
from ride_machine.service.core.motion.controllers import RotateRevolutions, TiltMove
from ride_machine.service.core.motion.devices import RotateCalibration
from ride_machine.service.core.motion.homing import Phase, RotateHome, TiltApproach
from ride_machine.service.core.motion.plausibility import RevolutionCheck
from ride_machine.service.core.scan.tasks import PendingCommand
from ride_machine.sim.settings import PhysicsParams
from tests.integration.support import FAST_CONFIG
from tests.rig import UNCOMMISSIONED, Rig, known_calibration

S = MachineState
C = Command
F = FaultCode
CONFIG = MachineConfig()
FAST = MachineConfig.model_validate(tomllib.loads(FAST_CONFIG.format(heartbeat_s=0.2)))
"""The integration tests' fast simulator (720°/s, a 1 s watchdog)."""
GAIN = CONFIG.hal.sim.ai_gain_counts_per_deg
ZERO = CONFIG.hal.sim.ai_offset_counts
TILT_SCAN_DEG = CONFIG.tilt.nominal_speed_dps * CONFIG.loop.period_s
ROTATE_SCAN_DEG = CONFIG.rotate.nominal_speed_dps * CONFIG.loop.period_s
SPEED_WINDOW_DEG = CONFIG.tilt.nominal_speed_dps * CONFIG.tilt.speed_window_s


def rig_on(**physics: float) -> Rig:
    return Rig(physics=PhysicsParams(tilt_min_deg=-12.0, **physics))


def offset_error_deg(rig: Rig) -> float:
    tilt = rig.state_machine.calibration.tilt
    assert tilt is not None, rig.state_machine.fault
    return abs(tilt.offset_counts - ZERO) / GAIN


def finish(rig: Rig, command: Command, **payload: object) -> MachineState:
    assert rig.send(command, **payload).success
    rig.run_until(lambda: rig.state not in (S.CALIBRATING, S.HOMING, S.RUNNING))
    return rig.state


def phases_of(
    rig: Rig, kind: type[TiltApproach | RotateHome], seen: list[Phase]
) -> Callable[[], bool]:
    """A `run_until` predicate that records each phase the `kind` controller passes."""

    def record() -> bool:
        ctl = rig.state_machine.motion()
        if isinstance(ctl, TiltCalibrate):
            ctl = ctl.homing
        phase = ctl.phase if isinstance(ctl, kind) else None
        if phase not in (None, Phase.START) and (not seen or seen[-1] is not phase):
            seen.append(phase)
        return rig.state not in (S.CALIBRATING, S.HOMING)

    return record


# -- 1. a defined approach: never latched where the switch was found closed ----------------
@pytest.mark.parametrize("start", [-10.0, -5.0, -0.05, 0.3, 12.0, 60.0])
def test_tilt_calibration_from_anywhere_measures_the_true_zero(start: float) -> None:
    """Issue 37, point 1: from -5° (the switch already closed) the offset was 1000 for 1200."""
    rig = rig_on(start_tilt_deg=start, tilt_home_hysteresis_deg=0.5)
    assert finish(rig, C.CALIBRATE_TILT) is S.WARNING_NEEDS_CALIBRATION
    assert offset_error_deg(rig) <= 0.25
    assert rig.hal.world.sense().tilt_home  # it ends at home, just past the edge


@pytest.mark.hazard("H17")
def test_a_switch_found_closed_is_backed_off_then_approached_from_above() -> None:
    rig = rig_on(start_tilt_deg=-5.0, tilt_home_hysteresis_deg=0.5)
    seen: list[Phase] = []
    assert rig.send(C.CALIBRATE_TILT).success
    rig.run_until(phases_of(rig, TiltApproach, seen))
    assert seen[:4] == [Phase.BACKOFF, Phase.RUNUP, Phase.DWELL, Phase.SEEK]


def test_home_from_on_the_switch_backs_off_and_lands_on_the_calibrated_zero() -> None:
    rig = Rig(calibration=known_calibration())
    rig.hal.place(tilt_deg=-3.0)
    seen: list[Phase] = []
    assert rig.send(C.HOME).success
    rig.run_until(phases_of(rig, TiltApproach, seen))
    assert rig.state is S.IDLE, rig.state_machine.fault
    assert seen[:4] == [Phase.BACKOFF, Phase.RUNUP, Phase.DWELL, Phase.SEEK]
    tilt = rig.state_machine.devices.tilt.read_position_degrees()
    assert tilt is not None and abs(tilt - rig.hal.world.tilt_deg) <= 0.25


# -- 2. the edge, not the scan: a late scan is approached again -----------------------------
def stall_at(rig: Rig, near: Callable[[], bool], stall_s: float, times: int) -> int:
    """Step to the end of the motion, each scan that `near()` comes `stall_s` late (at most
    `times` of them); how many came late."""
    late = 0
    while rig.state in (S.CALIBRATING, S.HOMING, S.RUNNING):
        stalled = late < times and near()
        late += stalled
        rig.clock.advance(stall_s if stalled else rig.period)
        rig.loop.step(rig.clock())
    return late


def test_a_tilt_edge_seen_across_a_stalled_scan_is_approached_again() -> None:
    """Issue 37, point 2: on a starved host the edge was seen when the scan happened to run,
    and the offset was 1173 for 1200. A scan 60 ms late at the edge (0.9° of travel) is not
    latched: the tilt backs off and comes down again."""
    rig = rig_on(start_tilt_deg=5.0)
    world = rig.hal.world
    assert rig.send(C.CALIBRATE_TILT).success
    cal = rig.state_machine.context.drive.controller
    assert isinstance(cal, TiltCalibrate)
    first = cal.homing

    def near() -> bool:
        return world.drive.tilt_on and not world.drive.tilt_up and 0.0 < world.tilt_deg < 0.3

    assert stall_at(rig, near, 0.06, times=1) == 1
    assert rig.state is S.WARNING_NEEDS_CALIBRATION, rig.state_machine.fault
    assert first is not None and first.attempts == 1
    assert "60 ms apart" in first.refused[0]
    assert offset_error_deg(rig) <= 0.25


@pytest.mark.hazard("H24", "H47")
def test_an_edge_stalled_at_every_approach_is_refused_never_done() -> None:
    rig = rig_on(start_tilt_deg=5.0)
    world = rig.hal.world

    def near() -> bool:
        return world.drive.tilt_on and not world.drive.tilt_up and 0.0 < world.tilt_deg < 0.3

    assert rig.send(C.CALIBRATE_TILT).success
    stall_at(rig, near, 0.06, times=100)
    assert rig.state is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.HOME_EDGE_UNCERTAIN and fault.axis == "tilt"
    assert fault.message.count("60 ms apart") == CONFIG.tilt.latch_attempts
    assert rig.state_machine.calibration.tilt is None
    assert not rig.relays_on()


def test_a_session_ending_across_a_stall_approaches_its_last_edge_again() -> None:
    """The rotate's last edge seen across a 40 ms gap (3.6°): where it stopped is known only to
    ±1.8°, so it is approached again from the defined side before DONE."""
    rig = Rig(calibration=known_calibration())
    rig.home()
    world = rig.hal.world
    assert rig.send(C.START, session=Session(steps=[RotateStep()]).model_dump()).success
    rig.step()
    revs = rig.state_machine.motion()
    assert isinstance(revs, RotateRevolutions)

    def near() -> bool:
        return revs.final is None and world.drive.rotate_on and world.rotate_deg > 358.0

    assert stall_at(rig, near, 0.04, times=1) == 1
    assert rig.state is S.DONE, rig.state_machine.fault
    assert revs.final is not None and revs.final.latch is not None
    assert rig.rotate_estimate_error_deg() <= CONFIG.rotate.latch_tolerance_deg


# -- 3. the rotate estimate: the world moves for the whole gap ------------------------------
def test_a_long_stall_mid_revolution_leaves_the_rotate_estimate_on_the_world() -> None:
    """Issue 37, point 3 (7.5° off once under heavy load): the simulator paused the rotate for
    every scan gap over half its arc's time (55 ms) while the estimate integrated the whole gap;
    a 138 ms gap put the estimate (138 - 55) ms × 90°/s = 7.5° ahead. Now the world moves for
    the whole gap (it pauses only where it would pass its whole switch unseen)."""
    rig = Rig(calibration=known_calibration())
    rig.home()
    world = rig.hal.world
    assert rig.send(C.START, session=Session(steps=[RotateStep()]).model_dump()).success
    rig.run_until(lambda: world.drive.rotate_on and 180.0 < world.rotate_deg < 200.0)
    rig.clock.advance(0.138)
    rig.loop.step(rig.clock())
    angle = rig.loop.axes.rotate.angle
    assert angle is not None
    assert abs(angle - world.rotate_deg) <= ROTATE_SCAN_DEG


# -- 4. plausibility: a gain typo stops within a few degrees -------------------------------
def enter(
    rig: Rig, tilt: TiltCalibrationSet | None = None, rotate: RotateCalibrationSet | None = None
) -> None:
    values = CalibrationSet(transaction_id="c", tilt=tilt, rotate=rotate)
    rig.state_machine.enter_calibration(values, rig.clock())
    rig.step()


@pytest.mark.hazard("H21")
@pytest.mark.parametrize("start", [-0.1, 12.0, 40.0])
def test_a_hand_entered_gain_typo_is_stopped_by_home_within_a_speed_window(start: float) -> None:
    """Issue 37, point 4: gain 400 for 40 (in range) drove the tilt into its end stop. Typed-in
    values need Home before Start; Home measures the speed and stops within one window."""
    rig = Rig(config=UNCOMMISSIONED, calibration=known_calibration())  # witnesses alone
    rig.home()
    rig.hal.place(tilt_deg=start)
    enter(rig, tilt=TiltCalibrationSet(offset_counts=1194.0, gain_counts_per_deg=400.0))
    refused = rig.send(C.START)
    assert refused.error is not None and refused.error.code == "NOT_HOME"
    assert finish(rig, C.HOME) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.TILT_SPEED_IMPLAUSIBLE, fault
    assert "gain 400" in fault.message
    assert abs(rig.hal.world.tilt_deg - start) <= SPEED_WINDOW_DEG + 2 * TILT_SCAN_DEG


@pytest.mark.hazard("H13")
def test_a_sensor_that_reads_a_tenth_stops_a_session_within_a_speed_window() -> None:
    rig = Rig(calibration=known_calibration())
    rig.home()
    world = rig.hal.world
    assert rig.send(C.START).success
    rig.run_until(
        lambda: isinstance(rig.state_machine.motion(), TiltMove) and world.tilt_deg > 10.0
    )
    broken = world.tilt_deg
    p = world.params
    tenth = p.ai_gain_counts_per_deg / 10
    offset = p.ai_offset_counts + (p.ai_gain_counts_per_deg - tenth) * broken  # no jump
    world.params = p.model_copy(
        update={"ai_gain_counts_per_deg": tenth, "ai_offset_counts": offset}
    )
    rig.run_to_state(S.FAULT_HW, max_s=5)
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.TILT_SPEED_IMPLAUSIBLE, fault
    assert world.tilt_deg - broken <= 2 * SPEED_WINDOW_DEG


@pytest.mark.hazard("H15", "H22", "H23")
def test_home_that_finds_the_edge_off_the_calibrated_zero_says_so() -> None:
    rig = Rig(calibration=known_calibration())
    rig.hal.world.params = rig.hal.world.params.model_copy(update={"tilt_home_deg": 1.0})
    assert finish(rig, C.HOME) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.HOME_OFF_ZERO, fault
    assert "+1.0" in fault.message


WIDE_LATCH = CONFIG.with_overrides(rotate={"latch_tolerance_deg": 1.0})
"""A rotate typed in faster than it is also judges its latches at that speed: room for it."""


@pytest.mark.hazard("H21", "H23")
def test_a_hand_entered_rotate_time_is_found_out_at_the_first_revolution() -> None:
    """The rotate has no sensor between its edges: a revolution time typed 50 % too long (in the
    accepted range) is found at the first closing edge, one revolution on."""
    rig = Rig(config=WIDE_LATCH, calibration=known_calibration())
    enter(rig, rotate=RotateCalibrationSet(revolution_s=6.0, home_arc_deg=10.0))
    rig.home()
    assert finish(rig, C.START, session=Session(steps=[RotateStep()]).model_dump()) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.ROTATE_SPEED_IMPLAUSIBLE, fault


@pytest.mark.hazard("H16")
def test_a_revolution_overdue_by_the_tolerance_stops_the_session() -> None:
    rig = Rig(config=WIDE_LATCH, calibration=known_calibration())
    enter(rig, rotate=RotateCalibrationSet(revolution_s=2.5, home_arc_deg=10.0))
    rig.home()
    assert rig.send(C.START, session=Session(steps=[RotateStep()]).model_dump()).success
    taken = rig.run_to_state(S.FAULT_HW, S.DONE, max_s=10)
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.ROTATE_HOME_TIMEOUT, fault
    assert taken == pytest.approx(2.5 * (1 + CONFIG.rotate.revolution_tolerance), abs=0.05)


# -- repeatability: two measurements that disagree are refused ------------------------------
@pytest.mark.hazard("H24")
def test_a_tilt_zero_that_moves_between_its_two_latches_is_refused() -> None:
    rig = rig_on(start_tilt_deg=5.0)
    assert rig.send(C.CALIBRATE_TILT).success
    cal = rig.state_machine.context.drive.controller
    assert isinstance(cal, TiltCalibrate)
    rig.run_until(lambda: len(cal.zeros) == 1)
    # The switch slips 0.5° down between the two latches (a loose cam).
    rig.hal.world.params = rig.hal.world.params.model_copy(update={"tilt_home_deg": -0.5})
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.CALIBRATION_NOT_REPEATABLE, fault
    first, second = (z.raw for z in cal.zeros)
    assert first is not None and second is not None
    assert f"{first:.1f}" in fault.message and f"{second:.1f}" in fault.message
    assert rig.state_machine.calibration.tilt is None


@pytest.mark.hazard("H24")
def test_a_rotate_whose_speed_changes_mid_calibration_is_refused() -> None:
    rig = Rig(calibration=known_calibration())
    assert rig.send(C.CALIBRATE_ROTATE).success
    rig.run_until(lambda: isinstance(rig.state_machine.motion(), RotateCalibrate))
    cal = rig.state_machine.motion()
    assert isinstance(cal, RotateCalibrate)
    rig.run_until(lambda: len(cal.edges) == 2)  # opening, closing: the first revolution's half
    rig.hal.world.params = rig.hal.world.params.model_copy(update={"rotate_speed_dps": 80.0})
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.CALIBRATION_NOT_REPEATABLE, fault
    assert "closing edges" in fault.message and "opening edges" in fault.message


def test_rotate_home_never_latches_the_edge_across_a_stall() -> None:
    rig = Rig(calibration=known_calibration())
    world = rig.hal.world
    assert rig.send(C.HOME).success
    homes: list[RotateHome] = []

    def near() -> bool:
        ctl = rig.state_machine.motion()
        if not isinstance(ctl, RotateHome):
            return False
        if ctl not in homes:
            homes.append(ctl)
        return ctl.phase is Phase.SEEK and world.rotate_deg > 359.0

    assert stall_at(rig, near, 0.04, times=1) == 1
    assert rig.state is S.IDLE, rig.state_machine.fault
    (home,) = homes
    assert home.attempts == 1 and "40 ms apart" in home.refused[0]
    assert rig.rotate_estimate_error_deg() <= CONFIG.rotate.latch_tolerance_deg


@pytest.mark.hazard("H47")
def test_a_revolution_hidden_by_two_stalls_is_a_fault_never_done() -> None:
    """Run 38 (a loaded host, the tests' fast config: 720°/s, a 1 s watchdog): a session ended
    DONE with 3 revolutions counted and 4 turned. One stall from the switch carried the rotate
    past the next arc; a second, before a cycle could call the revolution overdue, ended in the
    arc after: one revolution counted for two. The edge itself now judges the revolution late."""
    rig = Rig(config=FAST)
    rig.calibrate()
    rig.home()
    world = rig.hal.world
    before = world.revolutions
    assert rig.send(
        C.START, session=Session(steps=[RotateStep(revolutions=3)]).model_dump()
    ).success
    step = rig.state_machine.context.drive.controller
    rig.run_until(lambda: isinstance(step.current, RotateRevolutions) and step.current.done == 1)
    assert world.rotate_switch.closed
    for stall in (0.56, 0.45):  # from the arc past the next one; then on into the one after
        rig.clock.advance(stall)
        rig.step()
    rig.run_to_state(S.FAULT_HW, S.DONE, max_s=10)
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.ROTATE_HOME_TIMEOUT, (fault, world.revolutions)
    assert "passed unseen" in fault.message
    assert world.revolutions - before == pytest.approx(3.0, abs=0.1)  # stopped at the edge


@pytest.mark.hazard("H24")
def test_a_tilt_stroke_the_scan_stalled_through_is_refused_as_spoiled() -> None:
    """Run 42: a stall took most of a 0.4 s calibration stroke, which then had 2 samples (one
    a scan) and was refused as if the sensor were unwired (`CALIBRATION_IMPLAUSIBLE`). Too few
    scans is the scan's fault: the refusal says so, and is one a stall causes."""
    rig = Rig(config=FAST)
    assert rig.send(C.CALIBRATE_TILT).success
    cal = rig.state_machine.context.drive.controller
    assert isinstance(cal, TiltCalibrate)
    rig.run_until(lambda: cal.phase.name == "STROKE")
    rig.step()
    rig.clock.advance(0.35)
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.CALIBRATION_NOT_REPEATABLE, fault
    assert "the scan stalled" in fault.message and "calibrate again" in fault.message


@pytest.mark.parametrize(("gap_s", "stall_named"), [(0.02, False), (0.05, True), (0.3, True)])
def test_an_overdue_revolution_names_a_stall_of_the_scan_that_could_hide_its_edge(
    gap_s: float, stall_named: bool
) -> None:
    """Run 46 (a loaded host, `machine supervise`, the fast config): a ride faulted
    ROTATE_HOME_TIMEOUT. At 720°/s the home switch is closed 0.042 s a turn; a scan stalled that
    long can miss it, and the supervised world (not the scan) moves the rotate. The fault now
    says so, with the stall it measured; a scan that never stalled so long is not blamed."""
    cal = RotateCalibration(revolution_s=0.5, home_arc_deg=30.0)
    check = RevolutionCheck(FAST.rotate, cal, Direction.CW)
    check.start(0.0)
    now, fault = 0.0, None
    while fault is None:
        now += gap_s if 0.1 <= now < 0.1 + FAST.loop.period_s else FAST.loop.period_s
        fault = check.overdue(now)
    assert fault.code is F.ROTATE_HOME_TIMEOUT
    assert ("the scan stalled" in fault.message) is stall_named, fault.message
    if stall_named:
        assert f"stalled {gap_s:.3f} s" in fault.message and "(0.042 s)" in fault.message


def test_a_drive_whose_first_write_comes_late_is_not_judged_slow() -> None:
    """A tilt drive's relay is written on at the end of its first cycle; a busy host that
    preempts the scan there starts the tilt late (a container run under load: 75 ms of a
    0.12 s speed window stood still, `TILT_SPEED_IMPLAUSIBLE` "35.3°/s"). The speed and
    follow windows start from the next reading, taken with the drive on."""
    rig = Rig(calibration=known_calibration())
    rig.home()
    stalled = rig.hal.stalled_s
    replies: list[object] = []
    rig.loop.inbox.put(PendingCommand(C.START, StartRequest(transaction_id="late"), replies.append))
    rig.hal.stall_scans(1.0, 0.5)  # the Start's cycle: its write of the tilt relay comes late
    rig.step()
    rig.hal.stall_scans(0.0, 0.0)
    assert len(replies) == 1
    assert isinstance(rig.state_machine.motion(), TiltMove)
    assert rig.hal.stalled_s - stalled > CONFIG.tilt.speed_window_s * CONFIG.tilt.speed_tolerance
    rig.run_to_state(S.DONE, S.FAULT_HW)
    assert rig.state is S.DONE, rig.state_machine.fault
