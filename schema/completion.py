"""Completion notices: how each motion command ended, on `machine/<id>/done/<transaction_id>`.

Like a ROS 2 action's result: every accepted motion command (Home, CalibrateTilt,
CalibrateRotate, Start) gets exactly one notice when it ends, and a Start refused by its
checks gets one too (the seed's "send WARNING…, stop session, send DONE"). A paused or
E-stopped motion has not ended yet: Resume continues it, Stop ends it `STOPPED`.
"""

from __future__ import annotations

from enum import StrEnum

from pydantic import Field

from ride_machine.schema import SCHEMA_VERSION

from .base import OpenWireModel
from .status import MachineState


class Outcome(StrEnum):
    """How a motion command ended; a reader meeting a newer outcome keeps its string."""

    DONE = "DONE"
    """It did what it was asked: Home homed, a calibration was measured and saved, a session
    ran."""
    STOPPED = "STOPPED"
    """A Stop (or the rider-loss `stop` policy) ended it, or a new motion replaced it."""
    FAULT_HW = "FAULT_HW"
    """A hardware fault ended it (a sensor timeout, an invalid session, the watchdog); `code`."""
    FAULT_ESTOP = "FAULT_ESTOP"
    """The E-stop halted it and it was not resumed: Home or a calibration replaced it."""
    REFUSED = "REFUSED"
    """Start checked and refused: not calibrated or not home (the WARNING state says which)."""
    STORAGE_FAILED = "STORAGE_FAILED"
    """A calibration was measured and is in use, but could not be saved (lost at a restart)."""
    ABORTED = "ABORTED"
    """The daemon shut down before it ended."""


class Completion(OpenWireModel):
    """The one notice that ends a motion command (published once, then queryable)."""

    schema_version: int = SCHEMA_VERSION
    machine_id: str
    transaction_id: str
    command: str
    """The command's name as in `Reply.command`, e.g. "Home", "CalibrateTilt", "Start"."""
    outcome: Outcome | str = Field(union_mode="left_to_right")
    code: str | None = None
    """Why, for scripts: a fault code (TILT_HOME_TIMEOUT, ESTOP…) or an error code
    (NOT_CALIBRATED, STORAGE_FAILED…); None for DONE."""
    reason: str = ""
    """Why, for people."""
    state: MachineState
    """The machine's state right after it ended (IDLE after Home, DONE after a session…)."""
    rider: str | None = None
    started_at: float
    """Wall-clock seconds when the command was accepted."""
    time: float
    """Wall-clock seconds when it ended."""
