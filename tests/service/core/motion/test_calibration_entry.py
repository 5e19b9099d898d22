"""Calibration values on the machine: measured ones say so and when; a technician's values
are validated like a measurement, refused while moving, recorded as manual and persisted."""

from __future__ import annotations

import pytest

from ride_machine.schema.calibration import (
    CalibrationSet,
    CalibrationSource,
    RotateCalibrationSet,
    TiltCalibrationSet,
)
from ride_machine.schema.commands import Command
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MachineState
from ride_machine.service.core.motion.devices import Calibration
from ride_machine.service.errors import MachineError
from tests.rig import Rig

S = MachineState
TILT = TiltCalibrationSet(offset_counts=1190.0, gain_counts_per_deg=40.5)
ROTATE = RotateCalibrationSet(revolution_s=4.05, home_arc_deg=10.2)


def entry(**values: object) -> CalibrationSet:
    return CalibrationSet.model_validate({"transaction_id": "cal1", **values})


def test_measured_calibration_says_measured_and_when() -> None:
    rig = Rig()
    assert rig.send(Command.CALIBRATE_TILT).success
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    tilt = rig.state_machine.calibration.tilt
    assert tilt is not None and tilt.source is CalibrationSource.MEASURED
    assert tilt.at is not None and abs(tilt.at - rig.clock()) < 1.0
    record = rig.loop.published.calibration
    assert record is not None and record.tilt is not None
    assert record.tilt.source is CalibrationSource.MEASURED and record.rotate is None


def test_values_entered_by_hand_are_manual_used_at_once_and_saved() -> None:
    rig = Rig()  # a bare machine: needs calibration
    assert rig.state is S.WARNING_NEEDS_CALIBRATION
    saved: list[Calibration] = []
    rig.state_machine.keeper.on_calibrated = saved.append
    ticket = rig.state_machine.enter_calibration(
        entry(tilt=TILT.model_dump(), rotate=ROTATE.model_dump()), rig.clock()
    )
    assert ticket is None
    cal = rig.state_machine.calibration
    assert cal.tilt is not None and cal.rotate is not None
    assert (cal.tilt.offset_counts, cal.tilt.gain_counts_per_deg) == (1190.0, 40.5)
    assert cal.tilt.source is cal.rotate.source is CalibrationSource.MANUAL
    assert cal.tilt.at == rig.clock()
    assert saved == [cal]
    assert rig.machine.devices.tilt.calibration == cal.tilt  # degrees use it at once
    assert rig.state is S.WARNING_NOT_HOME  # calibrated now; never assumed home
    rig.step()
    record = rig.loop.published.calibration
    assert record is not None and record.complete and record.rotate is not None
    assert record.rotate.source is CalibrationSource.MANUAL
    assert record.rotate.speed_dps == pytest.approx(360 / 4.05)


def test_one_axis_keeps_the_other_axis_values() -> None:
    rig = Rig()
    rig.state_machine.enter_calibration(entry(rotate=ROTATE.model_dump()), rig.clock())
    rig.state_machine.enter_calibration(entry(tilt=TILT.model_dump()), rig.clock())
    cal = rig.state_machine.calibration
    assert cal.rotate is not None and cal.rotate.revolution_s == 4.05


@pytest.mark.hazard("H21")
@pytest.mark.parametrize(
    ("values", "code", "path"),
    [
        ({"tilt": {"offset_counts": 1190.0, "gain_counts_per_deg": 4.0}}, "PARAM_OUT_OF_RANGE",
         "/tilt/gain_counts_per_deg"),
        ({"rotate": {"revolution_s": 9.0, "home_arc_deg": 10.0}}, "PARAM_OUT_OF_RANGE",
         "/rotate/revolution_s"),
        ({}, "BAD_PAYLOAD", "/tilt"),
    ],
)  # fmt: skip
def test_implausible_values_are_refused_and_change_nothing(
    values: dict[str, object], code: str, path: str
) -> None:
    rig = Rig()
    with pytest.raises(MachineError) as info:
        rig.state_machine.enter_calibration(entry(**values), rig.clock())
    assert (info.value.code, info.value.path) == (ErrorCode(code), path)
    assert (
        rig.state_machine.calibration.tilt is None and rig.state_machine.calibration.rotate is None
    )


@pytest.mark.hazard("H21")
def test_values_are_refused_while_a_motion_is_under_way_or_paused() -> None:
    rig = Rig()
    assert rig.send(Command.CALIBRATE_TILT).success
    rig.step(3)
    for state in (S.CALIBRATING, S.PAUSED):
        assert rig.state is state
        with pytest.raises(MachineError) as info:
            rig.state_machine.enter_calibration(entry(tilt=TILT.model_dump()), rig.clock())
        assert info.value.code is ErrorCode.WRONG_STATE
        if state is S.CALIBRATING:
            assert rig.send(Command.PAUSE).success
    assert rig.state_machine.calibration.tilt is None


def test_the_wire_refuses_bad_numbers() -> None:
    for bad in ({"offset_counts": float("nan"), "gain_counts_per_deg": 40.0},
                {"offset_counts": 1.0, "gain_counts_per_deg": -1.0}):  # fmt: skip
        with pytest.raises(ValueError):
            entry(tilt=bad)
    with pytest.raises(ValueError):
        entry(rotate={"revolution_s": 4.0, "home_arc_deg": 200.0})
