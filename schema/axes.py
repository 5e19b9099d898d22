"""The FastData-style axis record published on `machine/<id>/axis/<name>`."""

from __future__ import annotations

from enum import IntFlag

from schema.base import OpenWireModel

AXIS_RECORD_VERSION = 1


class PnStatus(IntFlag):
    """Axis status bits, as in the motion controller's FastData stream."""

    SETTLED = 1 << 0
    MOVING = 1 << 1
    DRIVE_ENABLED = 1 << 2
    DRIVE_FAULT = 1 << 3


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
