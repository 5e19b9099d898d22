"""Axis records (FastData style) built from the devices each cycle.

Positions: the tilt reads its analog input (known once calibrated); the rotate has no encoder, so
`RotateEstimator` dead-reckons it from the drive time and re-references it at every home-switch
edge. `pn_status` follows seed 002: settled means no move is active or held *and* the position is
within the settle window of the last move's target (see `schema.axes.PnStatus`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ride_machine.schema.axes import ROTATE_AXIS_NUMBER, TILT_AXIS_NUMBER, AxisRecord, PnStatus
from ride_machine.schema.commands import Direction
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import LiveConfig, MachineConfig

from .base import Controller
from .calibrate import RotateCalibrate
from .controllers import RotateRevolutions
from .devices import Devices, RotateCalibration, TiltDirection
from .homing import RotateHome

AXIS_NUMBERS = {"rotate": ROTATE_AXIS_NUMBER, "tilt": TILT_AXIS_NUMBER}
# Plain ints: `IntFlag` arithmetic runs Python code in `enum`, several times a cycle.
MOVING = int(PnStatus.MOVING)
SETTLED = int(PnStatus.SETTLED)
DRIVE_ENABLED = int(PnStatus.DRIVE_ENABLED)
DRIVE_FAULT = int(PnStatus.DRIVE_FAULT)
POSITION_UNKNOWN = int(PnStatus.POSITION_UNKNOWN)


@dataclass
class AxisSample:
    """One axis at one instant, plain floats: cheap to make every cycle."""

    position_cmd: float
    position_fb: float
    velocity_cmd: float
    velocity_fb: float
    status: int
    known: bool
    drive_cmd: float
    drive_fb: float


class RotateEstimator:
    """Rotate angle from the home switch edges and the drive time (there is no encoder).

    The outputs written in one cycle move the axis until the next, so each update integrates
    the direction driven in the *previous* cycle (`drive()` records it after the update), and a
    switch edge is referenced with that direction even when the controller dropped the relay in
    the very cycle it saw the edge (Home does). The switch closes at 0° turning CW and opens at
    0° turning CCW; it closes at the end of its arc turning CCW and opens there turning CW.
    An edge happened somewhere between the scan before and this one: the angle is latched at
    the midpoint, half the travel since the scan before past the edge (sure to ± that much;
    the controllers approach again when that is too much, service/core/motion/homing.py).
    """

    def __init__(self) -> None:
        self.angle: float | None = None
        self.turns = 0.0
        """Signed revolutions since the reference (multi-turn, CW positive): the drive unit."""
        self.velocity = 0.0
        """°/s over the last interval, from the drive (signed, CW positive)."""
        self._last_home: bool | None = None
        self._driven: Direction | None = None

    def update(
        self,
        dt: float,
        home: bool,
        speed: float,
        arc: float,
        homing: bool = False,
        since_edge: float | None = None,
    ) -> None:
        """`dt`: the time since the last update's outputs were written; `since_edge`: from the
        midpoint between the last two input scans to this update's outputs (default `dt / 2`:
        outputs written as the inputs are read). `homing`: a Home (or the homing of a
        calibration) runs, so an edge restarts the turn count from the reference instead of
        continuing it."""
        driven = self._driven
        self.velocity = 0.0 if driven is None else (speed if driven is Direction.CW else -speed)
        if self.angle is not None and dt > 0:
            step = self.velocity * dt
            self.angle = (self.angle + step) % 360.0
            self.turns += step / 360.0
        last, self._last_home = self._last_home, home
        if driven is not None and last is not None and home != last:
            edge = 0.0 if home == (driven is Direction.CW) else arc
            late = dt / 2 if since_edge is None else since_edge
            self._latch(edge + self.velocity * late, homing)

    def drive(self, direction: Direction | None) -> None:
        """The direction this cycle's outputs drive until the next update."""
        self._driven = direction

    def forget(self) -> None:
        """The reference is gone (a hardware fault): unknown until the next switch edge."""
        self.angle = None
        self.turns = 0.0

    def _latch(self, deg: float, restart: bool) -> None:
        frac = deg / 360.0
        keep = self.angle is not None and not restart
        self.turns = round(self.turns - frac) + frac if keep else frac
        self.angle = deg % 360.0


class AxisTracker:
    """Keeps both axes' samples up to date and says when a record is worth publishing."""

    def __init__(self, devices: Devices, live: LiveConfig) -> None:
        self.devices = devices
        self.live = live
        self.rotate = RotateEstimator()
        self._last_t: float | None = None
        self._last_w: float | None = None
        """When the last update's outputs were written (the rotate moves from write to write)."""
        self._tilt_prev: float | None = None
        self._tilt_prev_cal: object = None
        """The calibration `_tilt_prev` was read through."""
        self._state: MachineState | None = None
        self.samples: dict[str, AxisSample] = {}
        # None: never published, so the first cycle publishes every axis once.
        self._last_status: dict[str, int | None] = {"rotate": None, "tilt": None}
        self._settling: set[str] = set()
        self._tilt_cal: object = None
        """The tilt calibration the last published tilt record was read through."""
        self.targets: dict[str, float | None] = {"rotate": None, "tilt": None}
        """Each axis' last move target (degrees), kept after the move ends or is stopped."""
        self._still: tuple[object, ...] | None = None
        self._steady = False

    @property
    def config(self) -> MachineConfig:
        return self.live.current

    def update(
        self,
        now: float,
        state: MachineState,
        fault_axis: str | None,
        rotate_cal: RotateCalibration | None,
        motion: Controller | None = None,
        written: float | None = None,
    ) -> None:
        """Sample both axes; `motion` is the controller owning an axis (running or held);
        `written`: when this cycle's outputs were written (default `now`)."""
        written = now if written is None else written
        last_t = now if self._last_t is None else self._last_t
        dt = now - last_t
        moved_for = 0.0 if self._last_w is None else written - self._last_w
        self._last_t, self._last_w = now, written
        if self._unchanged(state, fault_axis, rotate_cal, motion):
            return
        if state is MachineState.FAULT_HW and self._state is not MachineState.FAULT_HW:
            self.rotate.forget()  # Home is required again; until then the angle is a guess
        self._state = state
        holding = motion.axis_name if motion is not None else None
        if motion is not None and motion.target_deg is not None:
            self.targets[motion.axis_name] = motion.target_deg
        enabled = 0 if state is MachineState.FAULT_ESTOP else DRIVE_ENABLED
        revs = motion if isinstance(motion, RotateRevolutions) else None
        homing = isinstance(motion, RotateHome | RotateCalibrate)
        since_edge = written - (last_t + now) / 2
        self.samples["rotate"] = self._rotate(
            (moved_for, since_edge), rotate_cal, holding == "rotate", enabled, revs, homing
        )
        if fault_axis == "rotate":
            self.samples["rotate"].status |= DRIVE_FAULT
        self.samples["tilt"] = self._tilt(dt, holding == "tilt", enabled)
        if fault_axis == "tilt":
            self.samples["tilt"].status |= DRIVE_FAULT

    def at_rest(self) -> bool:
        """The next `update` with the same inputs returns at once and `due` is empty: both
        samples are steady (`_unchanged`), nothing moves and no axis owes a settled record."""
        if not self._steady or self._still is None or self._settling:
            return False
        if self.devices.tilt.calibration is not self._tilt_cal:
            return False
        return all(not s.status & MOVING for s in self.samples.values())

    def tick(self, now: float) -> None:
        """A quiet cycle (`at_rest` and every input as before): what `update` would do."""
        self._last_t = self._last_w = now

    def _unchanged(
        self,
        state: MachineState,
        fault_axis: str | None,
        rotate_cal: RotateCalibration | None,
        motion: Controller | None,
    ) -> bool:
        """At rest (no motion, no drive), with every input to the samples as in the last two
        cycles: the samples would come out as they are. Most idle cycles stop here."""
        rotate, tilt = self.devices.rotate, self.devices.tilt
        driven = rotate.driven_direction() is not None or tilt.driven_direction() is not None
        if motion is not None or driven:
            self._still = None
            return False
        still = (
            state,
            fault_axis,
            rotate_cal,
            tilt.calibration,
            rotate.is_home(),
            tilt.read_raw(),
            self.live.current,
            self.targets["rotate"],
            self.targets["tilt"],
        )
        if still != self._still:
            self._still, self._steady = still, False
            return False
        if self._steady:
            return True
        self._steady = True  # this cycle's samples, from the same inputs, are the steady ones
        return False

    def _rotate(
        self,
        times: tuple[float, float],
        cal: RotateCalibration | None,
        holding: bool,
        enabled: int,
        revs: RotateRevolutions | None,
        homing: bool,
    ) -> AxisSample:
        cfg = self.config.rotate
        speed, arc = cfg.nominal_speed_dps, cfg.home_arc_deg
        if cal is not None:  # measured beats nominal
            speed, arc = cal.speed_dps, cal.home_arc_deg
        rotate, est = self.devices.rotate, self.rotate
        moved_for, since_edge = times  # the drive's time, and from the edge to the write
        est.update(moved_for, rotate.is_home(), speed, arc, homing, since_edge)
        driven = rotate.driven_direction()
        est.drive(driven)
        angle, target = est.angle, self.targets["rotate"]
        error = 0.0 if angle is None or target is None else _wrap(target - angle)
        pos = 0.0 if angle is None else angle
        turns = est.turns if angle is not None else 0.0
        turns_cmd = turns + error / 360.0
        if revs is not None and angle is not None:
            turns_cmd = _end_turns(turns, revs, arc)
        return AxisSample(
            position_cmd=pos if target is None or angle is None else target,
            position_fb=pos,
            velocity_cmd=0.0 if driven is None else (speed if driven is Direction.CW else -speed),
            velocity_fb=est.velocity,
            status=_bits(
                known=angle is not None,
                moving=driven is not None,
                enabled=enabled,
                settled=not holding and abs(error) <= cfg.settle_window_deg,
            ),
            known=angle is not None,
            drive_cmd=turns_cmd,
            drive_fb=turns,
        )

    def _tilt(self, dt: float, holding: bool, enabled: int) -> AxisSample:
        tilt_axis = self.devices.tilt
        cal = tilt_axis.calibration
        tdir = tilt_axis.driven_direction()
        raw = tilt_axis.read_raw()
        tilt = tilt_axis.read_position_degrees()
        target = self.targets["tilt"]
        tv = self.config.tilt.nominal_speed_dps
        error = 0.0 if tilt is None or target is None else target - tilt
        # Positions read through one calibration only: one entered meanwhile moves every
        # reading at once, which is no speed (issue 58: a standing tilt "at -321°/s").
        prev = self._tilt_prev if self._tilt_prev_cal is cal else None
        velocity_fb = _rate(prev, tilt, dt)
        self._tilt_prev, self._tilt_prev_cal = tilt, cal
        raw_cmd = float(raw)
        if cal is not None and target is not None:
            raw_cmd = cal.offset_counts + cal.gain_counts_per_deg * target
        return AxisSample(
            position_cmd=(0.0 if tilt is None else tilt) if target is None else target,
            position_fb=0.0 if tilt is None else tilt,
            velocity_cmd=0.0 if tdir is None else (tv if tdir is TiltDirection.UP else -tv),
            velocity_fb=velocity_fb,
            status=_bits(
                known=tilt is not None,
                moving=tdir is not None,
                enabled=enabled,
                settled=not holding and abs(error) <= self.config.tilt.tolerance_deg,
            ),
            known=tilt is not None,
            drive_cmd=raw_cmd,
            drive_fb=float(raw),
        )

    def due(self, cycle: int) -> list[str]:
        """Axes to publish this cycle: every Nth cycle while moving, whenever the status bits
        change (moving, drive enabled by the E-stop, fault), once more the cycle after a stop,
        so the last record says settled with zero velocity, and the tilt whenever its
        calibration changed (entered by hand at rest: the same bits, another position)."""
        out = []
        every = self.config.bus.axis_every_cycles
        recal = self.devices.tilt.calibration is not self._tilt_cal
        for name, sample in self.samples.items():
            moving = bool(sample.status & MOVING)
            last = self._last_status[name]
            if (
                (moving and cycle % every == 0)
                or sample.status != last
                or name in self._settling
                or (recal and name == "tilt")
            ):
                out.append(name)
            if name in self._settling:
                self._settling.discard(name)
            elif last is not None and last & MOVING and not moving:
                self._settling.add(name)
            self._last_status[name] = sample.status
        if "tilt" in out:
            self._tilt_cal = self.devices.tilt.calibration
        return out

    def record(self, name: str, cycle: int, time: float) -> AxisRecord:
        s = self.samples[name]
        return AxisRecord(
            axis=name,
            axis_number=AXIS_NUMBERS[name],
            pn_status=s.status,
            cycle=cycle,
            position_cmd=s.position_cmd,
            position_fb=s.position_fb,
            velocity_cmd=s.velocity_cmd,
            velocity_fb=s.velocity_fb,
            time=time,
            position_known=s.known,
            drive_cmd=s.drive_cmd,
            drive_fb=s.drive_fb,
        )


def _bits(*, known: bool, moving: bool, enabled: int, settled: bool) -> int:
    bits = enabled
    if moving:
        bits |= MOVING
    if not known:
        bits |= POSITION_UNKNOWN
    elif settled and not moving:
        bits |= SETTLED
    return bits


def _end_turns(turns: float, revs: RotateRevolutions, arc: float) -> float:
    """Where (in turns) a revolutions move ends: on its remaining-th closing switch edge."""
    left = max(revs.total - revs.done, 1)
    if revs.direction is Direction.CW:  # closing edges at whole turns
        return math.floor(turns) + left
    a = arc / 360.0  # turning CCW the switch closes at the end of its arc
    return math.ceil(turns - a) - 1 + a - (left - 1)


def _wrap(delta: float) -> float:
    """An angle difference in [-180, 180)."""
    return (delta + 180.0) % 360.0 - 180.0


def _rate(prev: float | None, cur: float | None, dt: float) -> float:
    if prev is None or cur is None or dt <= 0:
        return 0.0
    return (cur - prev) / dt
