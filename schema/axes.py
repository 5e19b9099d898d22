"""The FastData-style axis record published on `machine/<id>/axis/<name>`."""

from __future__ import annotations

from enum import IntFlag

from .base import OpenWireModel

AXIS_RECORD_VERSION = 1


class PnStatus(IntFlag):
    """Axis status bits, as in the motion controller's FastData stream (seed 002).

    Bits 0-3 are the seed's; bit 4 is ours, from the range the seed leaves unused (always 0
    there), so a reader that knows only the seed's bits reads an unknown position as not settled.
    """

    SETTLED = 1 << 0
    """No move is active or held (paused, E-stop) and |target − position| ≤ the settle window."""
    MOVING = 1 << 1
    """The axis' drive relay is energised."""
    DRIVE_ENABLED = 1 << 2
    """The drive has power: clear while the E-stop is in FAULT_ESTOP."""
    DRIVE_FAULT = 1 << 3
    """The axis caused the current hardware fault."""
    POSITION_UNKNOWN = 1 << 4
    """The position is not referenced (rotate: not homed since start-up or a fault; tilt: not
    calibrated): position fields read 0.0 and mean nothing."""


ROTATE_AXIS_NUMBER = 1
"""The rotate axis' number (FastData request cell 0)."""
TILT_AXIS_NUMBER = 2
"""The tilt axis' number (FastData request cell 1)."""


class AxisRecord(OpenWireModel):
    """One axis at one cycle; old readers ignore fields added by newer versions."""

    version: int = AXIS_RECORD_VERSION
    axis: str
    axis_number: int
    pn_status: int
    cycle: int
    position_cmd: float
    position_fb: float
    velocity_cmd: float
    velocity_fb: float
    time: float
    position_known: bool = True
    """False until the position is referenced (then `pn_status` has POSITION_UNKNOWN)."""
    drive_cmd: float = 0.0
    """The commanded position in drive units (tilt: raw analog counts; rotate: turns since the
    home reference); FastData's `cCmd`."""
    drive_fb: float = 0.0
    """The position feedback in drive units; FastData's `cFb`."""
