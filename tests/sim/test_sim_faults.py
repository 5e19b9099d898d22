"""The simulator HAL's fault injection (stuck switches, a frozen or noisy analog input, stalled
drives) and scans stalled by a slow host (moved from test_sim.py)."""

from __future__ import annotations

import pytest

from ride_machine.hal.iomap import Signal
from ride_machine.service.config.model import MachineConfig
from ride_machine.sim.physics import SwitchFault
from ride_machine.sim.settings import PhysicsParams
from tests.sim.test_sim import DT, PARAMS, Sim, rising_edges


@pytest.mark.parametrize(
    ("fault", "expected"), [(SwitchFault.STUCK_OPEN, False), (SwitchFault.STUCK_CLOSED, True)]
)
def test_rotate_home_stuck(fault: SwitchFault, expected: bool) -> None:
    sim = Sim()
    sim.hal.stick_home("rotate", fault)
    sim.set(rotate=True)
    readings = [s["rotate_home"] for s in sim.run(8.0)]  # two revolutions
    assert set(readings) == {expected}
    sim.hal.stick_home("rotate", None)
    readings = [s["rotate_home"] for s in sim.run(4.0)]
    assert set(readings) == {True, False}


@pytest.mark.parametrize(
    ("fault", "expected"), [(SwitchFault.STUCK_OPEN, False), (SwitchFault.STUCK_CLOSED, True)]
)
def test_tilt_home_stuck(fault: SwitchFault, expected: bool) -> None:
    sim = Sim()
    sim.hal.stick_home("tilt", fault)
    sim.set(tilt=True)  # down through 0° to the lower limit
    readings = [s["tilt_home"] for s in sim.run(2.0)]
    assert sim.world.tilt_deg < 0.0
    assert set(readings) == {expected}


def test_frozen_analog_input_holds_its_last_value() -> None:
    sim = Sim()
    sim.set(tilt=True, tilt_up=True)
    held = sim.run(DT)[-1]["tilt_raw"]
    sim.hal.freeze_tilt_ai()
    readings = [s["tilt_raw"] for s in sim.run(2.0)]
    assert set(readings) == {held}
    assert sim.world.tilt_deg > PARAMS.start_tilt_deg + 20  # it still moved
    sim.hal.freeze_tilt_ai(False)
    assert sim.run(DT)[-1]["tilt_raw"] > held


def test_noisy_analog_input_scatters_within_its_amplitude() -> None:
    sim = Sim()
    true_raw = sim.run(DT)[-1]["tilt_raw"]
    sim.hal.set_tilt_noise(100)
    readings = [int(s["tilt_raw"]) for s in sim.run(2.0)]
    assert all(abs(r - true_raw) <= 100 for r in readings)
    assert max(readings) - min(readings) > 100  # really noisy, not a constant offset
    assert len(set(readings)) > 50


def test_noise_is_reproducible_from_the_seed() -> None:
    def noisy(seed: int) -> list[int]:
        sim = Sim(PhysicsParams(seed=seed))
        sim.hal.set_tilt_noise(50)
        return [int(s["tilt_raw"]) for s in sim.run(0.5)]

    assert noisy(5) == noisy(5)
    assert noisy(5) != noisy(6)


@pytest.mark.parametrize("axis", ["rotate", "tilt"])
def test_stalled_drive_gets_power_but_does_not_move(axis: str) -> None:
    sim = Sim()
    sim.hal.stall(axis)
    sim.set(rotate=True, tilt=True, tilt_up=True)
    sim.run(2.0)
    moved_rotate = sim.world.rotate_travel_deg != 0.0
    moved_tilt = sim.world.tilt_deg != PARAMS.start_tilt_deg
    assert (moved_rotate, moved_tilt) == ((False, True) if axis == "rotate" else (True, False))
    assert sim.hal.relay(Signal.ROTATE_RELAY)
    assert sim.hal.relay(Signal.TILT_RELAY)


def test_clear_faults_restores_every_sensor_and_drive() -> None:
    sim = Sim()
    hal = sim.hal
    hal.stick_home("rotate", SwitchFault.STUCK_CLOSED)
    hal.stick_home("tilt", SwitchFault.STUCK_CLOSED)
    hal.freeze_tilt_ai()
    hal.set_tilt_noise(30)
    hal.stall("rotate")
    hal.stall("tilt")
    hal.press_estop()
    hal.clear_faults()
    f = sim.world.faults
    assert (f.rotate_home, f.tilt_home, f.tilt_ai_frozen, f.tilt_ai_noise_counts) == (
        None,
        None,
        False,
        0.0,
    )
    assert not f.rotate_stalled
    assert not f.tilt_stalled
    assert f.estop_pressed  # the E-stop is a button, not a fault: released on its own


def test_fault_injection_refuses_bad_arguments() -> None:
    hal = Sim().hal
    with pytest.raises(ValueError, match="unknown axis"):
        hal.stick_home("lift", SwitchFault.STUCK_OPEN)
    with pytest.raises(ValueError, match="unknown axis"):
        hal.stall("lift")
    with pytest.raises(ValueError, match=">= 0"):
        hal.set_tilt_noise(-1)


@pytest.mark.parametrize("ccw", [False, True], ids=["cw", "ccw"])
def test_a_stalled_scan_never_lets_the_world_jump_past_the_home_switch(ccw: bool) -> None:
    start = 20.0 if ccw else 350.0  # 10° short of the switch either way
    sim = Sim(PhysicsParams(start_rotate_deg=start, home_arc_deg=10.0))
    sim.set(rotate=True, rotate_ccw=ccw)
    sim.clock.advance(1.0)  # the host stalled the scan thread for 1 s: 90° at 90°/s
    sim.hal.scan_inputs()
    # It pauses in the middle of the arc, the switch closed: seen, not jumped over.
    assert abs(sim.world.revolutions) * 360.0 == pytest.approx(15.0)
    assert sim.world.rotate_deg == pytest.approx(5.0)
    seen = [s["rotate_home"] for s in sim.run(20.0 / PARAMS.rotate_speed_dps)]
    assert seen[0] and rising_edges(seen) == 0


def test_a_stall_short_of_skipping_the_switch_moves_the_whole_gap() -> None:
    """A real ride turns on while the scan is late: the world integrates the whole gap, the
    tilt always, the rotate wherever it cannot pass its whole home switch unseen."""
    sim = Sim(PhysicsParams(start_rotate_deg=100.0, start_tilt_deg=10.0))
    sim.set(rotate=True, tilt=True, tilt_up=True)
    sim.clock.advance(0.5)
    sim.hal.scan_inputs()
    assert sim.world.rotate_deg == pytest.approx(145.0)
    assert sim.world.tilt_deg == pytest.approx(17.5)


def test_a_session_on_a_stalling_host_turns_exactly_its_revolutions() -> None:
    """Once per revolution, just before the switch, the scan comes 300 ms late (27° at 90°/s,
    past the whole 10° home arc): the session still ends on its third closing edge, three
    revolutions on, not four or more. That last edge, seen across the stall, is approached
    again from the defined side (the final approach, not stalled), so the angle reported at
    the end is the world's."""
    from ride_machine.schema.commands import Command
    from ride_machine.schema.status import MachineState
    from ride_machine.service.core.motion.controllers import RotateRevolutions
    from tests.rig import Rig

    rig = Rig().ready()
    start = rig.hal.world.revolutions
    assert rig.send(Command.START).success
    stalls, finals = 0, 0
    for _ in range(20_000):
        if rig.state is not MachineState.RUNNING:
            break
        revs = rig.state_machine.motion()
        counting = isinstance(revs, RotateRevolutions) and revs.final is None
        finals += isinstance(revs, RotateRevolutions) and revs.final is not None
        approaching = (
            counting and rig.hal.world.rotate_deg > 358.0 and rig.hal.world.drive.rotate_on
        )
        stalls += approaching
        rig.clock.advance(0.3 if approaching else rig.period)
        rig.loop.step(rig.clock())
    assert stalls >= 3
    assert rig.state is MachineState.DONE, rig.state_machine.fault
    assert finals > 0
    assert rig.hal.world.revolutions - start == pytest.approx(3.0, abs=0.02)
    angle = rig.loop.axes.rotate.angle
    assert angle is not None
    error = (angle - rig.hal.world.rotate_deg + 180.0) % 360.0 - 180.0
    assert abs(error) <= MachineConfig().rotate.latch_tolerance_deg
