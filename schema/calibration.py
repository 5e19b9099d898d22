"""Calibration on the bus: read on `machine/<id>/calibration`, entered by hand on
`machine/<id>/calibration/set` (seed 004's scaling factor, seed 000's datastore)."""

from __future__ import annotations

from enum import StrEnum

from pydantic import Field, FiniteFloat

from ride_machine.schema import SCHEMA_VERSION

from .base import OpenWireModel, WireModel
from .commands import TransactionId


class CalibrationSource(StrEnum):
    """How a calibration value came to be."""

    MEASURED = "measured"
    """Measured by CalibrateTilt / CalibrateRotate."""
    MANUAL = "manual"
    """Entered by a technician (`calibration/set`)."""


class TiltCalibrationValues(OpenWireModel):
    """Raw counts = offset + gain × degrees (the tilt's analog scaling)."""

    offset_counts: float
    gain_counts_per_deg: float
    source: CalibrationSource | None = None
    """None: a file from before sources were recorded (measured then)."""
    at: float | None = None
    """When it was measured or entered (wall-clock seconds); None if unknown."""
    verified: bool | None = None
    """Confirmed by the machine's witnesses (the home switch, the drive's speed): measured, or
    entered by hand and verified by a Home since. False: entered, and the next Home verifies
    it before any session may run on it. None: a machine from before verification."""


class RotateCalibrationValues(OpenWireModel):
    """The measured revolution time and home-switch arc (the rotate's scaling)."""

    revolution_s: float
    home_arc_deg: float
    speed_dps: float
    """360 / revolution_s, what the position estimate uses."""
    source: CalibrationSource | None = None
    at: float | None = None


class CalibrationRecord(OpenWireModel):
    """The machine's calibration now; an axis is null until calibrated."""

    schema_version: int = SCHEMA_VERSION
    machine_id: str
    tilt: TiltCalibrationValues | None = None
    rotate: RotateCalibrationValues | None = None
    complete: bool = False
    time: float


class TiltCalibrationSet(WireModel):
    """Tilt values a technician enters (checked against this machine's plausible gain range)."""

    offset_counts: FiniteFloat
    gain_counts_per_deg: FiniteFloat = Field(gt=0)


class RotateCalibrationSet(WireModel):
    """Rotate values a technician enters (checked against the nominal speed ± tolerance)."""

    revolution_s: FiniteFloat = Field(gt=0)
    home_arc_deg: FiniteFloat = Field(gt=0, lt=180)


class CalibrationSet(WireModel):
    """Enter one or both axes' calibration by hand; refused while a motion is under way."""

    transaction_id: TransactionId
    timecode: FiniteFloat | None = None
    tilt: TiltCalibrationSet | None = None
    rotate: RotateCalibrationSet | None = None
