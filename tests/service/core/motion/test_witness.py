"""The witnesses on the fake clock (issue 53, docs/homing.md): the home switch and the drive's
one speed check every tilt reference every time they can: an entered calibration is verified by
Home before anything rides on it, and a measured one that has since gone wrong is stopped with
the code of the witness that caught it, before the tilt passes its target by 1°."""

from __future__ import annotations

import random

import pytest

from ride_machine.schema.calibration import CalibrationSet, CalibrationSource
from ride_machine.schema.commands import Command, Session, TiltStep
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.witness import StrokeFit, judge_entered
from tests.rig import UNCOMMISSIONED, Rig, known_calibration

S = MachineState
C = Command
F = FaultCode
CONFIG = MachineConfig()
GAIN = CONFIG.hal.sim.ai_gain_counts_per_deg
ZERO = CONFIG.hal.sim.ai_offset_counts


def finish(rig: Rig, command: Command, **payload: object) -> MachineState:
    assert rig.send(command, **payload).success
    rig.run_until(lambda: rig.state not in (S.CALIBRATING, S.HOMING, S.RUNNING))
    return rig.state


def enter(rig: Rig, offset: float, gain: float) -> None:
    tilt = {"offset_counts": offset, "gain_counts_per_deg": gain}
    values = CalibrationSet.model_validate({"transaction_id": "typed", "tilt": tilt})
    rig.state_machine.enter_calibration(values, rig.clock())
    rig.step()


def tilt_to(degrees: float) -> dict[str, object]:
    return {"session": Session(name="to", steps=[TiltStep(degrees=degrees)]).model_dump()}


def drift(rig: Rig, gain_factor: float = 1.0, offset_deg: float = 0.0) -> None:
    """The sensor changes under a standing tilt (a slipped coupling, a replaced sensor): its
    gain by `gain_factor` about where the tilt stands, and it reads `offset_deg` more."""
    world = rig.hal.world
    p = world.params
    gain = p.ai_gain_counts_per_deg * gain_factor
    here = p.ai_offset_counts + p.ai_gain_counts_per_deg * world.tilt_deg
    offset = here - gain * world.tilt_deg + offset_deg * gain
    world.params = p.model_copy(update={"ai_gain_counts_per_deg": gain, "ai_offset_counts": offset})


def test_a_stroke_fit_measures_the_slope_and_how_sure_it_is() -> None:
    rng = random.Random(1)
    fit = StrokeFit()
    for i in range(200):
        fit.add(10.0 + i * 0.01, round(1200 + 600 * i * 0.01 + rng.uniform(-2, 2)))
    assert fit.slope() == pytest.approx(600.0, rel=0.005)
    assert 0.0 < fit.slope_error() < 1.0  # counts/s, from 200 samples over 2 s
    assert fit.span_s == pytest.approx(1.99)
    empty = StrokeFit()
    empty.add(1.0, 5)
    assert empty.slope() == 0.0 and empty.slope_error() == float("inf")


def test_judging_an_entered_calibration_names_the_witness_and_the_figure() -> None:
    from ride_machine.service.core.motion.devices import TiltCalibration

    cfg = CONFIG.tilt
    right = TiltCalibration(ZERO, GAIN, CalibrationSource.MANUAL, None, False)
    assert judge_entered(right, ZERO + 2.0, GAIN * 1.001, cfg) is None
    gain = judge_entered(TiltCalibration(ZERO, 52.0, verified=False), ZERO, GAIN, cfg)
    assert gain is not None and gain.code is F.TILT_GAIN_MISMATCH
    assert "40.00 counts/° against 52 entered (-23.1%)" in gain.message
    zero = judge_entered(TiltCalibration(ZERO + 40.0, GAIN, verified=False), ZERO, GAIN, cfg)
    assert zero is not None and zero.code is F.HOME_OFF_ZERO and "-1.00°" in zero.message


@pytest.mark.hazard("H21")
def test_the_issue_calibration_is_stopped_by_home_and_never_ridden() -> None:
    """Issue 53, point 1 on the fake clock: 1197 / 52 for the measured 1197 / 40."""
    rig = Rig(config=UNCOMMISSIONED, calibration=known_calibration())  # witnesses alone
    enter(rig, 1197.0, 52.0)
    assert rig.state_machine.calibration.tilt is not None
    assert rig.state_machine.calibration.tilt.verified is False
    assert finish(rig, C.HOME) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.TILT_GAIN_MISMATCH, fault
    assert not rig.relays_on() and rig.hal.world.tilt_deg < CONFIG.tilt.max_deg
    refused = rig.send(C.START)
    assert refused.error is not None and refused.error.code == "WRONG_STATE"  # FAULT_HW


def test_a_right_entry_is_verified_by_home_and_shown_verified() -> None:
    rig = Rig(calibration=known_calibration())
    enter(rig, ZERO, GAIN)
    record = rig.loop.published.calibration
    assert record is not None and record.tilt is not None and record.tilt.verified is False
    assert finish(rig, C.HOME) is S.IDLE, rig.state_machine.fault
    tilt = rig.state_machine.calibration.tilt
    assert tilt is not None and tilt.verified and tilt.source is CalibrationSource.MANUAL
    rig.step()
    record = rig.loop.published.calibration
    assert record is not None and record.tilt is not None and record.tilt.verified is True
    assert finish(rig, C.START, **tilt_to(60.0)) is S.DONE
    reported = rig.state_machine.devices.tilt.read_position_degrees()
    assert reported is not None and abs(reported - rig.hal.world.tilt_deg) <= 0.1


def test_calibrate_rotate_verifies_an_entered_tilt_on_its_way() -> None:
    rig = Rig(config=UNCOMMISSIONED, calibration=known_calibration())  # witnesses alone
    enter(rig, ZERO + 200.0, GAIN)  # 5° off
    assert finish(rig, C.CALIBRATE_ROTATE) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.HOME_OFF_ZERO, fault


@pytest.mark.hazard("H15", "H22", "H23")
@pytest.mark.parametrize("factor", [0.98, 0.97, 0.95])
def test_a_gain_that_drifted_stops_a_session_before_it_passes_its_target_by_a_degree(
    factor: float,
) -> None:
    """A measured calibration, then the sensor reads a few % less per degree: the calibration
    says less than the truth, so a session would overshoot (1.2° at 60° for 2 %); the stroke's
    speed gives it away first."""
    rig = Rig(calibration=known_calibration())
    rig.home()
    drift(rig, gain_factor=factor)
    highest = 0.0

    def ended() -> bool:
        nonlocal highest
        highest = max(highest, rig.hal.world.tilt_deg)
        return rig.state is not S.RUNNING

    assert rig.send(C.START, **tilt_to(60.0)).success
    rig.run_until(ended)
    fault = rig.state_machine.fault
    assert rig.state is S.FAULT_HW and fault is not None, rig.state
    assert fault.code is F.TILT_GAIN_MISMATCH, fault
    assert highest < 60.0 + 1.0


def session_with_drift(rig: Rig, steps: list[float], after: int, **change: float) -> MachineState:
    """A session through `steps` (degrees), the sensor drifting (`drift`) once step `after`
    is done; how it ended."""
    session = Session(name="drift", steps=[TiltStep(degrees=d) for d in steps])
    assert rig.send(C.START, session=session.model_dump()).success
    run = rig.state_machine.context.drive.session_run
    assert run is not None
    rig.run_until(lambda: run.index > after or rig.state is not S.RUNNING)
    drift(rig, **change)
    rig.run_until(lambda: rig.state is not S.RUNNING)
    return rig.state


@pytest.mark.hazard("H15")
def test_a_zero_that_moved_is_found_at_the_next_pass_down_through_the_switch() -> None:
    """The sensor slips 1° after a ride up: the way down to 0° passes the switch, which closes
    at "+1.0°" by the calibration."""
    rig = Rig(calibration=known_calibration())
    rig.home()
    assert session_with_drift(rig, [30.0, 0.0], after=0, offset_deg=1.0) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.HOME_OFF_ZERO, fault
    assert "closed on the way down at +1.0" in fault.message


@pytest.mark.hazard("H13")
def test_below_zero_by_the_calibration_the_switch_must_be_closed() -> None:
    """A zero that moved the other way: a session down to -1° stops short of the switch, which
    is still open where the calibration says it is below 0°."""
    config = CONFIG.with_overrides(tilt={"min_deg": -2.0})
    rig = Rig(config=config, calibration=known_calibration())
    rig.home()
    assert session_with_drift(rig, [10.0, -1.0], after=0, offset_deg=-1.5) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is F.HOME_OFF_ZERO, fault
    assert "is still open" in fault.message


def test_a_measured_calibration_rides_on_a_stalling_host_without_a_false_witness() -> None:
    """The witnesses judge a whole stroke by its fit: scans stalled up to 50 ms thin the samples
    out and leave a right calibration right."""
    rig = Rig(calibration=known_calibration())
    rig.hal.stall_scans(0.2, 0.05)
    rig.hal.set_tilt_noise(3.0)
    for _ in range(3):
        rig.home()
        steps = [TiltStep(degrees=d) for d in (60.0, 0.0, 45.0, 5.0, 60.0)]
        session = Session(name="up-and-down", steps=steps).model_dump()
        assert finish(rig, C.START, session=session) is S.DONE, rig.state_machine.fault
    assert rig.hal.stalled_s > 1.0


def test_a_home_whose_rotate_fails_keeps_the_tilts_verification() -> None:
    rig = Rig(calibration=known_calibration())
    enter(rig, ZERO, GAIN)
    rig.hal.stall("rotate")  # the rotate's home times out after the tilt's part passed
    assert finish(rig, C.HOME) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.axis == "rotate", fault
    tilt = rig.state_machine.calibration.tilt
    assert tilt is not None and tilt.verified
