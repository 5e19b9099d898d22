"""Axis records (FastData style) built from the devices each cycle."""

from __future__ import annotations

from dataclasses import dataclass

from schema.axes import AxisRecord, PnStatus
from schema.commands import Direction
from schema.status import MachineState
from service.config import MachineConfig
from service.devices import Devices, RotateCalibration, TiltDirection

ROTATE_AXIS_NUMBER = 0
TILT_AXIS_NUMBER = 1


@dataclass
class AxisSample:
    """One axis at one instant, plain floats: cheap to make every cycle."""

    position_cmd: float
    position_fb: float
    velocity_cmd: float
    velocity_fb: float
    status: int


class RotateEstimator:
    """Rotate angle from the home switch edges and the drive time (there is no encoder)."""

    def __init__(self) -> None:
        self.angle: float | None = None
        self._last_home: bool | None = None

    def update(
        self, dt: float, driven: Direction | None, home: bool, speed: float, arc: float
    ) -> None:
        if self.angle is not None and driven is not None:
            step = speed * dt if driven is Direction.CW else -speed * dt
            self.angle = (self.angle + step) % 360.0
        if home and self._last_home is False and driven is not None:
            self.angle = 0.0 if driven is Direction.CW else arc
        self._last_home = home


class AxisTracker:
    """Keeps both axes' samples up to date and says when a record is worth publishing."""

    def __init__(self, devices: Devices, config: MachineConfig) -> None:
        self.devices = devices
        self.config = config
        self.rotate = RotateEstimator()
        self._last_t: float | None = None
        self._tilt_prev: float | None = None
        self.samples: dict[str, AxisSample] = {}
        # None: never published, so the first cycle publishes every axis once.
        self._last_status: dict[str, int | None] = {"rotate": None, "tilt": None}
        self._settling: set[str] = set()
        self.tilt_target: float | None = None

    def update(
        self,
        now: float,
        state: MachineState,
        fault_axis: str | None,
        rotate_cal: RotateCalibration | None,
    ) -> None:
        dt = 0.0 if self._last_t is None else now - self._last_t
        self._last_t = now
        dev = self.devices
        cal = dev.tilt.calibration
        rot_speed = self.config.rotate.nominal_speed_dps
        arc = 0.0
        if rotate_cal is not None:  # measured beats nominal
            rot_speed, arc = rotate_cal.speed_dps, rotate_cal.home_arc_deg
        driven = dev.rotate.driven_direction()
        prev_angle = self.rotate.angle
        self.rotate.update(dt, driven, dev.rotate.is_home(), rot_speed, arc)
        enabled = 0 if state is MachineState.FAULT_ESTOP else PnStatus.DRIVE_ENABLED
        angle = self.rotate.angle
        vcmd = 0.0 if driven is None else (rot_speed if driven is Direction.CW else -rot_speed)
        self.samples["rotate"] = AxisSample(
            position_cmd=0.0 if angle is None else angle,
            position_fb=0.0 if angle is None else angle,
            velocity_cmd=vcmd,
            velocity_fb=_rate(prev_angle, angle, dt, wrap=True),
            status=_bits(driven is not None, enabled, fault_axis == "rotate"),
        )
        tdir = dev.tilt.driven_direction()
        tilt = dev.tilt.read_position_degrees()
        tv = self.config.tilt.nominal_speed_dps
        self.samples["tilt"] = AxisSample(
            position_cmd=self.tilt_target if self.tilt_target is not None else (tilt or 0.0),
            position_fb=0.0 if tilt is None else tilt,
            velocity_cmd=0.0 if tdir is None else (tv if tdir is TiltDirection.UP else -tv),
            velocity_fb=_rate(self._tilt_prev, tilt, dt, wrap=False),
            status=_bits(tdir is not None, enabled, fault_axis == "tilt") if cal else 0,
        )
        self._tilt_prev = tilt

    def due(self, cycle: int) -> list[str]:
        """Axes to publish this cycle: every Nth cycle while moving, whenever the status bits
        change (moving, drive enabled by the E-stop, fault), and once more the cycle after a
        stop, so the last record says settled with zero velocity."""
        out = []
        every = self.config.bus.axis_every_cycles
        for name, sample in self.samples.items():
            moving = bool(sample.status & PnStatus.MOVING)
            last = self._last_status[name]
            if (moving and cycle % every == 0) or sample.status != last or name in self._settling:
                out.append(name)
            if name in self._settling:
                self._settling.discard(name)
            elif last is not None and last & PnStatus.MOVING and not moving:
                self._settling.add(name)
            self._last_status[name] = sample.status
        return out

    def record(self, name: str, cycle: int, time: float) -> AxisRecord:
        s = self.samples[name]
        return AxisRecord(
            axis=name,
            axis_number=ROTATE_AXIS_NUMBER if name == "rotate" else TILT_AXIS_NUMBER,
            pn_status=s.status,
            cycle=cycle,
            position_cmd=s.position_cmd,
            position_fb=s.position_fb,
            velocity_cmd=s.velocity_cmd,
            velocity_fb=s.velocity_fb,
            time=time,
        )


def _bits(moving: bool, enabled: int, fault: bool) -> int:
    bits = enabled
    bits |= PnStatus.MOVING if moving else PnStatus.SETTLED
    if fault:
        bits |= PnStatus.DRIVE_FAULT
    return int(bits)


def _rate(prev: float | None, cur: float | None, dt: float, *, wrap: bool) -> float:
    if prev is None or cur is None or dt <= 0:
        return 0.0
    delta = cur - prev
    if wrap:
        delta = (delta + 180.0) % 360.0 - 180.0
    return delta / dt
