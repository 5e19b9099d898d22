"""What the scan loop publishes, and where to: `LoopSink` (a method per publication, called on
the scan thread), and `Published`, the latest records as one immutable value other threads read."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, TypeVar

from pydantic import BaseModel

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import (
    CalibrationRecord,
    RotateCalibrationValues,
    TiltCalibrationValues,
)
from ride_machine.schema.completion import Completion
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import Status
from ride_machine.service.core.motion.devices import Calibration

W = TypeVar("W", bound=BaseModel)


class LoopSink(Protocol):
    """Where the loop's publications go (the Zenoh bus, or lists in tests); the loop's one
    outbound channel. Called on the scan thread: never block."""

    def publish_status(self, status: Status) -> None: ...

    def publish_io(self, points: list[IoValue]) -> None: ...

    def publish_axes(self, records: list[AxisRecord]) -> None: ...

    def publish_completion(self, notice: Completion) -> None:
        """A motion ended, after the status it ends with."""
        ...

    def publish_calibration(self, record: CalibrationRecord) -> None:
        """The calibration changed (measured, entered by hand, or at start-up)."""
        ...


class NullSink:
    """Publishes nothing."""

    def publish_status(self, status: Status) -> None:
        pass

    def publish_io(self, points: list[IoValue]) -> None:
        pass

    def publish_axes(self, records: list[AxisRecord]) -> None:
        pass

    def publish_completion(self, notice: Completion) -> None:
        pass

    def publish_calibration(self, record: CalibrationRecord) -> None:
        pass


@dataclass(frozen=True, slots=True)
class Published:
    """The latest records, as one value: the loop replaces it whole, so any thread may read
    it (`LoopPort.published`) without a lock."""

    status: Status | None = None
    calibration: CalibrationRecord | None = None
    io: dict[str, IoValue] = field(default_factory=dict)
    axes: dict[str, AxisRecord] = field(default_factory=dict)


def calibration_record(cal: Calibration, machine_id: str, wall: float) -> CalibrationRecord:
    """The wire record of a calibration (values, how and when each axis got them)."""
    return CalibrationRecord(
        machine_id=machine_id,
        tilt=_wire(TiltCalibrationValues, cal.tilt),
        rotate=_wire(RotateCalibrationValues, cal.rotate),
        complete=cal.complete,
        time=wall,
    )


def _wire(model: type[W], values: object | None) -> W | None:
    """One axis' calibration as its wire model (the same field names); None stays None."""
    return None if values is None else model.model_validate(values, from_attributes=True)
