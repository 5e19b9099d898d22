"""Whole sessions on the simulator: from power-up to DONE, custom sessions, pause and stop."""

from __future__ import annotations

import pytest

from ride_machine.hal.iomap import Signal
from ride_machine.schema.commands import Command, Direction, Reply, RotateStep, Session, TiltStep
from ride_machine.schema.commands import CommandRequest as Req
from ride_machine.schema.status import AxesFlags, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.controllers import SessionRun
from ride_machine.service.core.scan.tasks import PendingCommand
from tests.rig import BAD_SESSION, Rig, known_calibration, rig_in

S = MachineState
C = Command

ROTATE_STEP_DEG = MachineConfig().hal.sim.rotate_speed_dps * MachineConfig().loop.period_s
"""How far the rotate axis turns in one cycle: the resolution of revolution counting."""
TILT_TOL = MachineConfig().tilt.tolerance_deg


def run_session(rig: Rig, **payload: object) -> tuple[float, list[tuple[int, float, float]]]:
    """Start, step to DONE; returns the rotate travel and (step index, tilt, travel) per cycle."""
    world = rig.hal.world
    travel0 = world.rotate_travel_deg
    reply = rig.send(C.START, **payload)
    assert reply.success, reply.error
    trace: list[tuple[int, float, float]] = []

    def record() -> bool:
        run = rig.state_machine.context.drive.session_run
        if run is not None:
            trace.append((run.index, world.tilt_deg, world.rotate_travel_deg - travel0))
        return rig.state is not S.RUNNING

    rig.run_until(record, max_s=300)
    assert rig.state is S.DONE, rig.state_machine.fault
    return world.rotate_travel_deg - travel0, trace


def test_full_default_session_from_power_up() -> None:
    rig = Rig()
    assert rig.state is S.WARNING_NEEDS_CALIBRATION
    assert not rig.relays_on()

    rig.calibrate()
    rig.home()
    assert rig.state is S.IDLE
    assert rig.hal.relay(Signal.ROTATE_RELAY) is False
    travel, trace = run_session(rig)

    # Exactly three revolutions, counted on the home switch, to within one cycle's travel.
    assert travel == pytest.approx(3 * 360.0, abs=ROTATE_STEP_DEG)
    # The tilt reached 45° (tilt step done) before the rotate moved, and stayed there.
    tilt_step = [(tilt, turned) for index, tilt, turned in trace if index == 0]
    rotate_step = [(tilt, turned) for index, tilt, turned in trace if index == 1]
    assert tilt_step
    assert rotate_step
    assert all(turned == 0.0 for _, turned in tilt_step)
    assert rotate_step[0][0] == pytest.approx(45.0, abs=TILT_TOL)
    assert {tilt for tilt, _ in rotate_step} == {rotate_step[0][0]}
    assert rig.hal.world.tilt_deg == pytest.approx(45.0, abs=TILT_TOL)
    # It stops on the rotate home switch, with every relay off.
    assert rig.hal.world.sense().rotate_home
    assert not rig.relays_on()

    status = rig.loop.published.status
    assert status is not None
    assert status.state == "DONE"
    assert status.previous_state == "RUNNING"
    assert status.session is not None
    assert status.session.revolutions_done == status.session.revolutions_total == 3
    assert status.tilt_deg == pytest.approx(45.0, abs=TILT_TOL)


def test_session_progress_is_published_while_running() -> None:
    rig = rig_in(S.IDLE)
    run_session(rig)
    seen = [
        (s.session.step_index, s.session.revolutions_done) for s in rig.sink.statuses if s.session
    ]
    assert (0, 0) in seen
    assert [done for _, done in seen if done] == sorted(done for _, done in seen if done)
    assert {1, 2, 3} <= {done for _, done in seen}
    running = [s for s in rig.sink.statuses if s.state == "RUNNING"]
    assert running
    assert all(s.session is not None and s.session.name == "default" for s in running)
    assert running[0].session is not None
    assert running[0].session.tilt_target_deg == 45.0


def test_custom_session_runs_every_step_in_order() -> None:
    rig = rig_in(S.IDLE)
    session = Session(
        name="mixed",
        steps=[
            TiltStep(degrees=30.0),
            RotateStep(direction=Direction.CCW, revolutions=2),
            TiltStep(degrees=10.0),
            RotateStep(direction=Direction.CW, revolutions=1),
        ],
    )
    travel, trace = run_session(rig, session=session.model_dump())

    by_step: dict[int, list[tuple[float, float]]] = {}
    for index, tilt, turned in trace:
        by_step.setdefault(index, []).append((tilt, turned))
    assert sorted(by_step) == [0, 1, 2, 3, 4]  # 4: the last step finished
    # Edge counting: a reversal shortens the first revolution by the home arc (10°).
    ccw_end = by_step[2][0][1]
    assert ccw_end == pytest.approx(-720.0, abs=ROTATE_STEP_DEG + 10.0)
    assert all(turned == ccw_end for _, turned in by_step[2])  # rotate idle while tilting
    assert by_step[1][0][0] == pytest.approx(30.0, abs=TILT_TOL)
    assert by_step[3][0][0] == pytest.approx(10.0, abs=TILT_TOL)
    # CCW revolutions end on the switch's far edge, CW ones on its near edge: net -1 turn.
    assert travel == pytest.approx(-360.0, abs=2 * ROTATE_STEP_DEG + 10.0)
    assert rig.hal.world.tilt_deg == pytest.approx(10.0, abs=TILT_TOL)


@pytest.mark.parametrize("revolutions", [1, 5])
def test_revolution_count_is_exact(revolutions: int) -> None:
    rig = rig_in(S.IDLE)
    session = Session(steps=[RotateStep(revolutions=revolutions)])
    travel, _ = run_session(rig, session=session.model_dump())
    assert travel == pytest.approx(360.0 * revolutions, abs=ROTATE_STEP_DEG)


def started() -> tuple[Rig, SessionRun, float]:
    """An idle rig that has just started the default session; its rotate travel before it."""
    rig = rig_in(S.IDLE)
    travel0 = rig.hal.world.rotate_travel_deg
    assert rig.send(C.START).success
    run = rig.state_machine.context.drive.session_run
    assert run is not None
    return rig, run, travel0


@pytest.mark.parametrize("pause_in_step", [0, 1], ids=["during-tilt", "during-rotate"])
def test_pause_freezes_everything_and_resume_finishes_the_session(pause_in_step: int) -> None:
    rig, run, travel0 = started()
    world = rig.hal.world
    rig.run_until(lambda: run.index == pause_in_step and rig.relays_on())
    rig.step(50)  # well into the step

    assert rig.send(C.PAUSE).success
    rig.step()
    assert not rig.relays_on()
    frozen = (world.tilt_deg, world.rotate_travel_deg)
    # Paused far longer than any timeout: paused time never counts against a controller.
    rig.step(3000)
    assert rig.state is S.PAUSED
    assert not rig.relays_on()
    assert (world.tilt_deg, world.rotate_travel_deg) == frozen

    reply = rig.send(C.RESUME)
    assert reply.state is S.RUNNING
    rig.run_to_state(S.DONE, S.FAULT_HW)
    assert rig.state is S.DONE, rig.state_machine.fault
    assert world.rotate_travel_deg - travel0 == pytest.approx(1080.0, abs=ROTATE_STEP_DEG)
    assert world.tilt_deg == pytest.approx(45.0, abs=TILT_TOL)


def test_stop_mid_session_drops_relays_and_clears_the_session() -> None:
    rig = rig_in(S.IDLE)
    assert rig.send(C.START).success
    run = rig.state_machine.context.drive.session_run
    assert run is not None
    rig.run_until(lambda: run.index == 1 and rig.relays_on())
    rig.step(30)
    reply = rig.send(C.STOP)
    assert reply.code == "RESP_DONE"
    rig.step()
    assert not rig.relays_on()
    where = rig.hal.world.rotate_travel_deg
    rig.step(500)
    assert rig.state is S.DONE
    assert rig.hal.world.rotate_travel_deg == where
    assert rig.state_machine.context.drive.session_run is None


def test_a_second_session_needs_home_and_then_runs_again() -> None:
    rig = rig_in(S.IDLE)
    run_session(rig)
    refused = rig.send(C.START)
    assert refused.error is not None
    assert refused.error.code == "NOT_HOME"
    assert rig.state is S.WARNING_NOT_HOME
    rig.home()
    travel, _ = run_session(rig)
    assert travel == pytest.approx(1080.0, abs=ROTATE_STEP_DEG)


@pytest.mark.hazard("H22", "H43")
def test_session_on_a_machine_calibrated_in_an_earlier_life() -> None:
    rig = Rig(calibration=known_calibration())
    assert rig.state is S.WARNING_NOT_HOME  # never assumed home after power-up
    assert not rig.relays_on()
    rig.home()
    travel, _ = run_session(rig)
    assert travel == pytest.approx(1080.0, abs=ROTATE_STEP_DEG)
    assert rig.hal.world.tilt_deg == pytest.approx(45.0, abs=TILT_TOL)


def test_session_with_a_slower_machine_still_counts_revolutions() -> None:
    """Rotate speed is a property of the machine: calibration learns it, counting follows."""
    config = MachineConfig().with_overrides(
        hal={"sim": {"rotate_speed_dps": 60.0}}, rotate={"nominal_speed_dps": 60.0}
    )
    rig = Rig(config=config)
    rig.calibrate()
    cal = rig.state_machine.calibration.rotate
    assert cal is not None
    assert cal.revolution_s == pytest.approx(6.0, abs=0.02)
    rig.home()
    travel, _ = run_session(rig)
    assert travel == pytest.approx(1080.0, abs=0.6)


@pytest.mark.parametrize("edge", [2, 3], ids=["an-edge", "the-last-edge"])
def test_an_edge_read_in_the_scan_that_pauses_is_counted(edge: int) -> None:
    """The scan that first reads the rotate's home switch closed may be the one that pauses
    the session (a Pause queued meanwhile, the deadman: both act before the controller's
    update), and its write may come late (a loaded host preempted the scan), so the rotate runs
    on past the switch before its relay drops. The edge still counts: the session ends after
    three revolutions of the world, not four (CI, tests/integration/test_session.py). The last
    edge so seen is approached again on Resume (where the rotate stopped is unknown), back
    through the switch, and the session ends on it."""
    rig, run, travel0 = started()
    world = rig.hal.world
    rig.run_until(lambda: run.revolutions_done() == edge - 1 and not world.sense().rotate_home)
    # Step until the next scan's read is the first to find the switch closed (at 0°).
    rig.run_until(lambda: world.rotate_deg + ROTATE_STEP_DEG >= 360.0)
    got: list[Reply] = []
    rig.loop.inbox.put(PendingCommand(C.PAUSE, Req(transaction_id="pause"), got.append))
    rig.hal.stall_scans(1.0, 0.5)  # the write comes up to 0.5 s late: past the 10° arc
    rig.step()
    rig.hal.stall_scans(0.0, 0.0)
    assert [r.code for r in got] == ["RESP_PAUSED"]
    assert rig.state is S.PAUSED
    assert not world.sense().rotate_home, "the rotate ran on past the switch"
    assert run.revolutions_done() == edge
    assert rig.send(C.RESUME).state is S.RUNNING
    rig.run_to_state(S.DONE, S.FAULT_HW)
    assert rig.state is S.DONE, rig.state_machine.fault
    assert world.sense().rotate_home and not rig.relays_on()
    assert world.rotate_travel_deg - travel0 == pytest.approx(1080.0, abs=2 * ROTATE_STEP_DEG)


def test_a_start_refused_for_its_session_keeps_the_home_references() -> None:
    """Issue 58, point 8: nothing moved, so both axes are as home as before; a Stop (out of
    FAULT_HW) and a good session ride without a Home."""
    rig = rig_in(MachineState.IDLE)
    assert not rig.send(Command.START, session=BAD_SESSION.model_dump()).success
    assert rig.state is MachineState.FAULT_HW
    assert rig.state_machine.keeper.homed() == AxesFlags(tilt=True, rotate=True)
    assert rig.send(Command.STOP).success
    rig.step()
    assert rig.send(Command.START).success, rig.replies[-1]
    rig.run_to_state(MachineState.DONE, MachineState.FAULT_HW)
    assert rig.state is MachineState.DONE, rig.state_machine.fault
