"""A tilt sensor whose wire breaks or shorts: found in the cycle it reads, at rest as in motion.

Before, a value no tilt can give was found only once the tilt was driven (its follow and speed
witnesses), or at rest when the calibration put it below zero with the switch open. The raw
value must now lie where the commissioned scale (any zero and gain in their bands) puts some
tilt from `tilt.min_deg` to `tilt.max_deg`, each widened by `tilt.signal_margin_deg`.
"""

from __future__ import annotations

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.scale import raw_envelope, signal_fault
from ride_machine.sim.physics import INT16_MAX
from tests.rig import Rig, known_calibration

S = MachineState
OPEN, SHORT = 0, INT16_MAX
"""What a broken wire reads: an open circuit nothing, a short to the supply full scale."""


def test_the_envelope_is_the_commissioned_scale_over_the_range_and_its_margin() -> None:
    tilt = MachineConfig().tilt  # 0..60°, zero 1160..1240, gain 38..42, margin 20°
    assert raw_envelope(tilt) == (1160 - 42 * 20, 1240 + 42 * 80)
    narrower = tilt.model_copy(update={"signal_margin_deg": 10.0})  # a parameter written
    assert raw_envelope(narrower) == (1160 - 42 * 10, 1240 + 42 * 70)
    assert raw_envelope(tilt) == (1160 - 42 * 20, 1240 + 42 * 80)
    lo, hi = raw_envelope(tilt)
    assert signal_fault(int(lo), tilt) is None and signal_fault(int(hi), tilt) is None
    assert signal_fault(int(lo) - 1, tilt) is not None
    fault = signal_fault(OPEN, tilt)
    assert fault is not None and fault.code is FaultCode.TILT_SIGNAL_RANGE
    assert (
        fault.axis == "tilt" and "reads 0 counts" in fault.message and "320..4600" in fault.message
    )


@pytest.mark.hazard("H13")
@pytest.mark.parametrize("reads", [OPEN, SHORT], ids=["open-circuit", "short"])
def test_a_broken_wire_at_rest_is_a_fault_in_the_cycle_it_reads(reads: int) -> None:
    rig = Rig(calibration=known_calibration())
    rig.home()
    assert rig.state is S.IDLE
    rig.hal.break_tilt_wire(reads)
    rig.step()  # the cycle that reads it
    assert rig.state is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is FaultCode.TILT_SIGNAL_RANGE
    assert f"reads {reads} counts" in fault.message
    assert not rig.relays_on()
    # Nothing moved: the references stand, and the wire repaired a Home is taken again.
    assert rig.loop.published.status is not None
    assert rig.loop.published.status.homed.tilt
    rig.hal.break_tilt_wire(None)
    assert rig.send(Command.HOME).success
    rig.run_until(lambda: rig.state is not S.HOMING)
    assert rig.state is S.IDLE


@pytest.mark.hazard("H13")
def test_a_wire_that_breaks_mid_session_stops_it_in_that_cycle() -> None:
    rig = Rig(calibration=known_calibration())
    rig.home()
    assert rig.send(Command.START).success
    rig.run_until(rig.relays_on)
    rig.hal.break_tilt_wire(OPEN)
    rig.step()
    assert rig.state is S.FAULT_HW and not rig.relays_on()
    assert rig.state_machine.fault is not None
    assert rig.state_machine.fault.code is FaultCode.TILT_SIGNAL_RANGE
    status = rig.loop.published.status
    assert status is not None and not status.homed.tilt  # it moved: Home again


@pytest.mark.hazard("H13")
def test_a_home_with_the_wire_still_broken_faults_before_any_relay() -> None:
    rig = Rig(calibration=known_calibration())
    rig.hal.break_tilt_wire(SHORT)
    rig.step()
    assert rig.state is S.FAULT_HW
    seat = (rig.hal.world.tilt_deg, rig.hal.world.rotate_deg)
    assert rig.send(Command.HOME).success  # a command takes it out of the fault ...
    rig.step(10)  # ... and the next cycle meets the wire again, before any output
    assert rig.state is S.FAULT_HW and not rig.relays_on()
    assert (rig.hal.world.tilt_deg, rig.hal.world.rotate_deg) == seat  # nothing moved
