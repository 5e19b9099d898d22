"""The charge pump (issue 53, docs/revpi.md): an output the scan toggles every cycle while the
machine is healthy, and the simulated external relay that keeps the drives' power only while it
toggles. A controller that stops as a whole — no scan, no watchdog thread, no supervisor —
cannot keep a drive powered past the relay's timeout."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from ride_machine.hal.base import Outputs
from ride_machine.hal.iomap import IoMap
from ride_machine.hal.revpi import RevPiHal
from ride_machine.schema.commands import Command, Session, TiltStep
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.sim.physics import ChargePumpRelay
from tests.fixtures.revpi import CONFIG_RSC, make_image, read_bit
from tests.rig import BAD_SESSION, Rig, known_calibration

S = MachineState
C = Command
PUMPED = MachineConfig().with_overrides(hal={"iomap": {"chargePump": "O_5"}})
TIMEOUT_S = PUMPED.hal.sim.charge_pump_timeout_s
TILT_DPS = PUMPED.hal.sim.tilt_speed_dps


def pumped_rig() -> Rig:
    return Rig(config=PUMPED, calibration=known_calibration())


def levels(rig: Rig, cycles: int) -> list[bool | None]:
    seen = []
    for _ in range(cycles):
        rig.step()
        seen.append(rig.loop.image.outputs.pump)
    return seen


def ride_the_tilt(rig: Rig) -> None:
    """Home, then a session to 45°, until the tilt is driven at 10°."""
    rig.home()
    session = Session(name="up", steps=[TiltStep(degrees=45.0)]).model_dump()
    assert rig.send(C.START, session=session).success
    rig.run_until(lambda: rig.hal.world.tilt_deg > 10.0)
    assert rig.hal.world.drive.tilt_on


@pytest.mark.hazard("H04")
def test_the_pump_changes_level_every_cycle_while_healthy_quiet_cycles_too() -> None:
    rig = pumped_rig()
    seen = levels(rig, 50)
    assert all(a is not b for a, b in itertools.pairwise(seen)), seen
    assert rig.loop.quiet > 20  # an idle machine's quiet cycles toggle it as well
    pump = rig.hal.world.pump
    assert pump is not None and pump.powered(rig.hal.world.time) and pump.drops == 0


def test_no_charge_pump_mapped_writes_none_and_the_world_has_no_relay() -> None:
    rig = Rig(calibration=known_calibration())
    assert set(levels(rig, 5)) == {None}
    assert rig.hal.world.pump is None


def test_a_fault_stops_the_pump_the_relay_drops_and_home_picks_it_up_again() -> None:
    rig = pumped_rig()
    rig.home()
    assert not rig.send(C.START, session=BAD_SESSION.model_dump()).success
    rig.step()
    assert rig.state is S.FAULT_HW
    assert set(levels(rig, 20)) == {False}
    world = rig.hal.world
    assert world.pump is not None and not world.pump.powered(world.time)
    assert rig.send(C.HOME).success
    rig.run_to_state(S.IDLE, S.FAULT_HW)
    assert rig.state is S.IDLE, rig.state_machine.fault
    assert world.pump.powered(world.time) and world.pump.drops == 1


@pytest.mark.hazard("H09", "H10")
def test_the_estop_holds_the_pump_low_until_the_machine_leaves_its_fault() -> None:
    rig = pumped_rig()
    rig.step(3)
    rig.hal.press_estop()
    assert set(levels(rig, 10)) == {False}
    rig.hal.release_estop()
    assert set(levels(rig, 10)) == {False}  # released, still latched: FAULT_ESTOP
    assert rig.send(C.STOP).success
    seen = levels(rig, 4)
    assert True in seen and False in seen


@pytest.mark.hazard("H01")
def test_a_latched_watchdog_writes_the_pump_low() -> None:
    rig = Rig(config=PUMPED, calibration=known_calibration(), guarded=True)
    assert rig.guard is not None
    ride_the_tilt(rig)
    rig.guard.latch_safe(0.2)
    world = rig.hal.world
    assert world.pump is not None and world.pump.level is False
    assert not rig.relays_on()


@pytest.mark.hazard("H02", "H03", "H05", "H44")
@pytest.mark.parametrize("pumped", [True, False])
def test_a_controller_frozen_as_a_whole_loses_drive_power_within_the_timeout(pumped: bool) -> None:
    """Issue 53, point 2 on the fake clock: the whole process stops for 5 s mid-ride (no
    scan, no thread of it runs), then runs one more scan. Without a charge pump the tilt ran
    the whole freeze, to its end stop; with one, the relay cut the drives `TIMEOUT_S` after the
    pump's last change."""
    rig = pumped_rig() if pumped else Rig(calibration=known_calibration())
    ride_the_tilt(rig)
    before = rig.hal.world.tilt_deg
    rig.clock.advance(5.0)
    rig.loop.step(rig.clock())  # the first scan after the freeze
    overrun = rig.hal.world.tilt_deg - before
    if pumped:
        assert overrun <= TILT_DPS * (TIMEOUT_S + 2 * rig.period)
    else:
        assert overrun > 40.0  # 75° of drive, stopped by the end stop at 95°


@pytest.mark.hazard("H44")
def test_the_relay_sees_a_level_change_as_an_edge_and_drops_after_the_last() -> None:
    relay = ChargePumpRelay(0.1)
    assert not relay.powered(0.0)  # no change yet: no power
    relay.feed(True, 1.0)
    relay.feed(True, 1.05)  # the same level is no edge
    assert relay.powered(1.1) and not relay.powered(1.1001)
    relay.feed(False, 1.2)  # after the drop: picked up again, one drop counted
    assert relay.powered(1.25) and relay.drops == 1
    relay.unseen(since=1.25, at=1.5)  # a world that looked away: retriggered where it looks
    assert relay.powered(1.6)
    relay.unseen(since=1.9, at=2.2)  # it had dropped before it looked away: stays dropped
    assert not relay.powered(2.2)


@pytest.mark.hazard("H44")
def test_the_revpi_hal_writes_the_pump_bit_and_leaves_it_out_of_energised(tmp_path: Path) -> None:
    image = make_image(tmp_path)
    hal = RevPiHal(IoMap(chargePump="O_5"), image, str(CONFIG_RSC))
    try:
        hal.scan_outputs(Outputs(ro={}, pump=True))
        assert read_bit(image, "O_5") is True
        assert not hal.energised()  # the pump is no relay of the ride
        hal.scan_outputs(Outputs(ro={"O_3": True}, pump=False))
        assert read_bit(image, "O_5") is False and hal.energised()
        hal.scan_outputs(Outputs(ro={}, pump=True))
        hal.force_all_outputs_safe()
        assert read_bit(image, "O_5") is False
    finally:
        hal.close()


@pytest.mark.hazard("H01")
def test_a_watchdog_trip_names_the_stall_and_the_pump_resumes_after_home() -> None:
    rig = Rig(config=PUMPED, calibration=known_calibration(), guarded=True)
    ride_the_tilt(rig)
    assert rig.guard is not None
    rig.guard.latch_safe(0.3)
    rig.step()
    fault = rig.state_machine.fault
    assert rig.state is S.FAULT_HW and fault is not None and fault.code is FaultCode.WATCHDOG
    assert set(levels(rig, 5)) == {False}
