"""Calibration values a technician enters by hand (`calibration/set`): checked against the same
plausible ranges a measurement must meet. Entering them clears the axis's home reference, so the
next Home checks them with a measured move before a session runs on them (docs/homing.md)."""

from __future__ import annotations

from ride_machine.schema.calibration import CalibrationSet, CalibrationSource
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.errors import BadRequest, ParamOutOfRange

from .devices import Calibration, RotateCalibration, TiltCalibration
from .scale import scale_problem


def manual_calibration(
    values: CalibrationSet, config: MachineConfig, current: Calibration, wall: float
) -> Calibration:
    """`current` with a technician's values (source manual, entered at `wall`), checked
    against the same plausible ranges a measurement must meet."""
    if values.tilt is None and values.rotate is None:
        raise BadRequest("give tilt values, rotate values or both", "/tilt")
    manual = CalibrationSource.MANUAL
    tilt, rotate = current.tilt, current.rotate
    if values.tilt is not None:
        t = values.tilt
        outside = scale_problem(t.offset_counts, t.gain_counts_per_deg, config.tilt)
        if outside is not None:
            raise ParamOutOfRange(outside.message, outside.path)
        # Unverified until a Home's stroke confirms it (`TiltVerify`).
        tilt = TiltCalibration(t.offset_counts, t.gain_counts_per_deg, manual, wall, False)
    if values.rotate is not None:
        r = values.rotate
        nominal = 360.0 / config.rotate.nominal_speed_dps
        tol = config.rotate.speed_tolerance
        if not nominal * (1 - tol) <= r.revolution_s <= nominal * (1 + tol):
            raise ParamOutOfRange(
                f"revolution time {r.revolution_s:g} s is outside {nominal:.3f} s ± {tol:.0%}"
                " (rotate.nominal_speed_dps, rotate.speed_tolerance)",
                "/rotate/revolution_s",
            )
        rotate = RotateCalibration(r.revolution_s, r.home_arc_deg, manual, wall)
    return Calibration(tilt=tilt, rotate=rotate)
