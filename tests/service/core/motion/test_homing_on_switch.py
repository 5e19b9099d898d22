"""Homing ends on the switch (docs/homing.md, "It ends on the switch"): the stop is written at the
end of the scan that read the edge, and a scan preempted before that write runs the axis on. Home,
CalibrateRotate and a session's last revolution end only when a scan after the stop still reads
the switch closed; else the edge is approached again. On the fake clock, with the write of the
latching scan made late (`Rig.step_late`)."""

from __future__ import annotations

import pytest

from ride_machine.schema.commands import Command, RotateStep, Session
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.calibrate import RotateCalibrate
from ride_machine.service.core.motion.controllers import RotateRevolutions
from ride_machine.service.core.motion.homing import Phase, RotateHome
from tests.rig import Rig, known_calibration

S = MachineState
C = Command
CONFIG = MachineConfig()
LATE_S = 0.3
"""A stop written this late runs the rotate (90°/s) 27° on: past its 10° arc and hysteresis."""
SIM_SCAN_DEG = CONFIG.hal.sim.rotate_speed_dps * CONFIG.loop.period_s
"""The world's rotate travel in one scan."""


def edge_next_scan(rig: Rig) -> bool:
    """Turning CW, the next scan's read is the first to find the rotate's switch closed."""
    world = rig.hal.world
    return (
        world.drive.rotate_on
        and not world.drive.rotate_ccw
        and not world.sense().rotate_home
        and world.rotate_deg + SIM_SCAN_DEG >= 360.0
    )


def on_the_switch(rig: Rig) -> None:
    """The world's rotate rests on its switch, where the machine's estimate says it is."""
    world = rig.hal.world
    assert world.sense().rotate_home and not rig.relays_on()
    assert rig.rotate_estimate_error_deg() <= CONFIG.rotate.latch_tolerance_deg


@pytest.mark.hazard("H18", "H19")
def test_a_home_whose_stop_is_written_late_approaches_again_and_ends_on_the_switch() -> None:
    """Run 61 (a loaded host, the tests' 720°/s): Home latched the rotate's edge, the scan was
    preempted before it wrote the stop, the rotate ran past its arc, and Home said DONE (the
    state IDLE, from that scan's read); the Start after it was refused `NOT_HOME`. Home ends
    only when a scan after the stop still reads the switch closed; this one did not, so the
    rotate backs off through the switch and approaches again."""
    rig = Rig(calibration=known_calibration())
    assert rig.send(C.HOME).success
    rig.run_until(
        lambda: isinstance(rig.state_machine.motion(), RotateHome) and edge_next_scan(rig)
    )
    home = rig.state_machine.motion()
    assert isinstance(home, RotateHome)
    rig.step_late(LATE_S)
    assert home.phase is Phase.STOPPED and home.latch is not None
    assert not rig.hal.world.sense().rotate_home, "the rotate ran on past the switch"
    rig.run_to_state(S.IDLE, S.WARNING_NOT_HOME, S.FAULT_HW)
    assert rig.state is S.IDLE, rig.state_machine.fault
    assert home.attempts == 1 and "off the switch" in home.refused[0], home.refused
    on_the_switch(rig)
    rig.step()  # a scan after the state said IDLE: Start reads the switch as it is now
    assert rig.send(C.START).success


@pytest.mark.hazard("H19")
def test_a_session_whose_last_stop_is_written_late_ends_on_the_switch() -> None:
    """The session's last edge latched well, its stop written late: the rotate is found past
    the switch and approached again, back through it (not a revolution more)."""
    rig = Rig(calibration=known_calibration())
    rig.home()
    travel0 = rig.hal.world.rotate_travel_deg
    session = Session(steps=[RotateStep(revolutions=2)])
    assert rig.send(C.START, session=session.model_dump()).success
    rig.step()
    revs = rig.state_machine.motion()
    assert isinstance(revs, RotateRevolutions)
    rig.run_until(lambda: revs.done == 1 and edge_next_scan(rig))
    rig.step_late(LATE_S)
    assert revs.done == 2 and revs.stopped is not None and revs.final is None
    assert not rig.hal.world.sense().rotate_home, "the rotate ran on past the switch"
    rig.run_to_state(S.DONE, S.FAULT_HW)
    assert rig.state is S.DONE, rig.state_machine.fault
    assert revs.final is not None and revs.final.latch is not None
    on_the_switch(rig)
    travel = rig.hal.world.rotate_travel_deg - travel0
    assert travel == pytest.approx(720.0, abs=CONFIG.rotate.latch_tolerance_deg + SIM_SCAN_DEG)


def test_a_rotate_calibration_whose_last_stop_is_written_late_ends_on_the_switch() -> None:
    """CalibrateRotate ends on its last closing edge; a stop written late there is found past
    the switch: the rotate is homed again, and what it measured is kept."""
    rig = Rig(calibration=known_calibration())
    assert rig.send(C.CALIBRATE_ROTATE).success
    rig.run_until(lambda: isinstance(rig.state_machine.motion(), RotateCalibrate))
    cal = rig.state_machine.motion()
    assert isinstance(cal, RotateCalibrate)

    def last_edge_next() -> bool:
        closings = sum(1 for closing, _ in cal.edges if closing)
        return cal.homing is None and closings == 1 and edge_next_scan(rig)

    rig.run_until(last_edge_next)
    rig.step_late(LATE_S)
    assert cal.result is not None and cal.stopped is not None
    assert not rig.hal.world.sense().rotate_home, "the rotate ran on past the switch"
    homes: list[RotateHome] = []

    def record() -> bool:
        if cal.homing is not None and cal.homing not in homes:
            homes.append(cal.homing)
        return rig.state is not S.CALIBRATING

    rig.run_until(record)
    assert rig.state is S.IDLE, rig.state_machine.fault
    assert len(homes) == 1 and homes[0].attempts == 0
    kept = rig.state_machine.calibration.rotate
    assert kept is not None
    assert (kept.revolution_s, kept.home_arc_deg) == (
        cal.result.revolution_s,
        cal.result.home_arc_deg,
    )
    on_the_switch(rig)
