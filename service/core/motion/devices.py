"""The device layer: the two axes and the safety input, in terms the controllers speak."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from ride_machine.schema.calibration import CalibrationSource
from ride_machine.schema.commands import Direction

from .io import AI, DI, RO, IoPoints


class TiltDirection(StrEnum):
    UP = "up"
    DOWN = "down"


@dataclass(frozen=True, slots=True)
class TiltCalibration:
    """Raw counts = offset + gain × degrees, as discovered by CalibrateTilt."""

    offset_counts: float
    gain_counts_per_deg: float
    source: CalibrationSource = CalibrationSource.MEASURED
    at: float | None = None
    """When it was measured or entered (wall-clock seconds)."""
    verified: bool = True
    """Confirmed by the machine's witnesses: measured, or entered by hand and since verified
    by a Home's stroke (docs/homing.md). An entered one is not, until then."""

    def degrees(self, raw: int) -> float:
        return (raw - self.offset_counts) / self.gain_counts_per_deg


@dataclass(frozen=True, slots=True)
class RotateCalibration:
    """The measured revolution time and home-switch arc, as discovered by CalibrateRotate."""

    revolution_s: float
    home_arc_deg: float
    source: CalibrationSource = CalibrationSource.MEASURED
    at: float | None = None

    @property
    def speed_dps(self) -> float:
        return 360.0 / self.revolution_s


@dataclass(frozen=True, slots=True)
class Calibration:
    """Everything calibration discovered; an axis is uncalibrated while its entry is None."""

    tilt: TiltCalibration | None = None
    rotate: RotateCalibration | None = None

    @property
    def complete(self) -> bool:
        return self.tilt is not None and self.rotate is not None


class _RelayAxis:
    """An axis driven by a relay and a direction output, with a home switch."""

    def __init__(self, relay: RO, direction: RO, home: DI) -> None:
        self.relay = relay
        self.direction = direction
        self.home = home

    def _energise(self, reverse: bool) -> None:
        self.direction.set(reverse)
        self.relay.set(True)

    def stop(self) -> None:
        self.relay.set(False)
        self.direction.set(False)

    def is_home(self) -> bool:
        return self.home.value


class RotateAxis(_RelayAxis):
    """Relay + direction output and a home switch that closes once per revolution."""

    def drive(self, direction: Direction) -> None:
        """Energise the drive in `direction` (revolutions are counted by the controller)."""
        self._energise(direction is Direction.CCW)

    def driven_direction(self) -> Direction | None:
        if not self.relay.value:
            return None
        return Direction.CCW if self.direction.value else Direction.CW


class TiltAxis(_RelayAxis):
    """Relay + direction output, an analog position in raw counts, a home switch at 0°."""

    def __init__(self, relay: RO, direction: RO, home: DI, position: AI) -> None:
        super().__init__(relay, direction, home)
        self.position = position
        self.calibration: TiltCalibration | None = None

    def drive(self, direction: TiltDirection) -> None:
        """Energise the drive up or down."""
        self._energise(direction is TiltDirection.UP)

    def driven_direction(self) -> TiltDirection | None:
        if not self.relay.value:
            return None
        return TiltDirection.UP if self.direction.value else TiltDirection.DOWN

    def read_raw(self) -> int:
        return self.position.value

    def read_position_degrees(self) -> float | None:
        """Degrees from the analog input, or None until the axis is calibrated."""
        if self.calibration is None:
            return None
        return self.calibration.degrees(self.position.value)


class Safety:
    """The E-stop input; wired normally closed unless the IO map says otherwise."""

    def __init__(self, estop: DI, active_low: bool) -> None:
        self.estop = estop
        self.active_low = active_low

    def is_estop_active(self) -> bool:
        level = self.estop.value
        return not level if self.active_low else level


class Devices:
    """The ride's devices over one set of IO points."""

    def __init__(self, points: IoPoints) -> None:
        self.points = points
        self.rotate = RotateAxis(points.rotate_relay, points.rotate_dir, points.rotate_home)
        self.tilt = TiltAxis(
            points.tilt_relay, points.tilt_dir, points.tilt_home, points.tilt_position
        )
        self.safety = Safety(points.estop, points.image.iomap.estop_active_low)

    def stop_all(self) -> None:
        self.rotate.stop()
        self.tilt.stop()
