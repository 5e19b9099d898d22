"""Non-blocking controllers: each `update(now)` looks at the inputs and sets the outputs once.

They read no clock (time comes in as `now`), touch no IO beyond the devices, and never block.
A controller ends `DONE` or `FAULT` (with a `Fault` saying why); `halt()` drops its outputs for a
pause or an E-stop and `resume(now)` restarts its timeout windows, so paused time never counts.
Every window is a `Timeout`; phases are enums; single-axis controllers share `AxisController`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from enum import Enum, auto
from typing import Generic, TypeVar

from schema.commands import Direction, RotateStep, Session, TiltStep
from schema.status import Fault, FaultCode, SessionProgress
from service.config.model import MachineConfig, RotateSection, TiltSection
from service.core.devices import (
    Devices,
    RotateAxis,
    RotateCalibration,
    TiltAxis,
    TiltCalibration,
    TiltDirection,
)


class Outcome(Enum):
    BUSY = auto()
    DONE = auto()
    FAULT = auto()


REVERSE_DWELL_S = 0.2
"""Relay off this long before a motor reverses, so a contactor never swaps direction under load."""


class Timeout:
    """A window timer in the manner of revpimodio2's Cycletools timers, on the time that comes
    in: `start(now, limit_s)`, then `elapsed(now)`; `expired(now)` once past the limit (a
    timeout), `done(now)` once the limit is reached (a dwell or a timed stroke is over).
    `resume(now)` starts the window again after a pause or an E-stop: paused time never counts."""

    __slots__ = ("_t0", "limit_s")

    def __init__(self, limit_s: float = 0.0) -> None:
        self.limit_s = limit_s
        self._t0: float | None = None

    @property
    def started(self) -> bool:
        return self._t0 is not None

    def start(self, now: float, limit_s: float | None = None) -> None:
        self._t0 = now
        if limit_s is not None:
            self.limit_s = limit_s

    def resume(self, now: float) -> None:
        self._t0 = now

    def stop(self) -> None:
        """Not running: the next `start` arms it afresh."""
        self._t0 = None

    def elapsed(self, now: float) -> float:
        assert self._t0 is not None, "a timer is read only once started"
        return now - self._t0

    def expired(self, now: float) -> bool:
        return self.elapsed(now) > self.limit_s

    def done(self, now: float) -> bool:
        return self.elapsed(now) >= self.limit_s


class Controller:
    """Base: a fault ends the controller with outputs stopped."""

    axis_name = ""
    target_deg: float | None = None
    """Where this controller leaves its axis (the settle check's target); None: nowhere fixed."""

    def __init__(self) -> None:
        self.fault: Fault | None = None

    def update(self, now: float) -> Outcome:
        raise NotImplementedError

    def halt(self) -> None:
        raise NotImplementedError

    def resume(self, now: float) -> None:
        raise NotImplementedError

    def abandon(self) -> None:
        """Stopped for good (Stop, Home over it): outputs off, nothing half-done kept."""
        self.halt()

    def active(self) -> Controller | None:
        """The controller doing the work now."""
        return self

    def _fault(self, fault: Fault) -> Outcome:
        self.halt()
        self.fault = fault
        return Outcome.FAULT

    def _fail(self, code: FaultCode, message: str) -> Outcome:
        return self._fault(Fault(code=code, message=message, axis=self.axis_name or None))

    def _step(self, sub: Controller, now: float) -> Outcome:
        """Run a sub-controller for one cycle; its fault is this controller's."""
        outcome = sub.update(now)
        if outcome is Outcome.FAULT:
            self.fault = sub.fault
        return outcome


AxisT = TypeVar("AxisT", RotateAxis, TiltAxis)
CfgT = TypeVar("CfgT", RotateSection, TiltSection)


class AxisController(Controller, Generic[AxisT, CfgT]):
    """One axis and its config section, with one `Timeout`: `halt()` stops the axis and
    `resume(now)` starts the window under way again."""

    def __init__(self, axis: AxisT, cfg: CfgT) -> None:
        super().__init__()
        self.axis: AxisT = axis
        self.cfg: CfgT = cfg
        self.timer = Timeout()

    def halt(self) -> None:
        self.axis.stop()

    def resume(self, now: float) -> None:
        self.timer.resume(now)


class Measurement(AxisController[AxisT, CfgT]):
    """A calibration: homing steps around a measurement. A paused homing step goes on; a
    paused measurement is worthless, so it re-homes and measures again."""

    homing: Controller | None
    """The homing step under way; None while measuring."""

    def resume(self, now: float) -> None:
        if self.homing is not None:
            self.homing.resume(now)
        else:
            self._start_over()

    def _start_over(self) -> None:
        raise NotImplementedError


# ---------------------------------------------------------------------------------- rotate
class HomePhase(Enum):
    START = auto()
    BACKOFF = auto()
    """On the switch: turn CCW until it opens."""
    DWELL = auto()
    """Relay off before reversing."""
    SEEK = auto()
    """Turn CW to the switch's closing edge."""


class RotateHome(AxisController[RotateAxis, RotateSection]):
    """Back off the switch if on it (CCW), dwell, then seek its closing edge CW."""

    axis_name = "rotate"
    target_deg = 0.0

    def __init__(self, axis: RotateAxis, cfg: RotateSection) -> None:
        super().__init__(axis, cfg)
        self.phase = HomePhase.START
        self._limits = {
            HomePhase.BACKOFF: cfg.backoff_timeout_s,
            HomePhase.DWELL: REVERSE_DWELL_S,
            HomePhase.SEEK: cfg.revolution_timeout_s,
        }

    def _enter(self, phase: HomePhase, now: float) -> None:
        self.phase = phase
        self.timer.start(now, self._limits[phase])

    def update(self, now: float) -> Outcome:
        home = self.axis.is_home()
        if self.phase is HomePhase.START:
            self._enter(HomePhase.BACKOFF if home else HomePhase.SEEK, now)
        if self.phase is HomePhase.BACKOFF:
            return self._back_off(now, home)
        if self.phase is HomePhase.DWELL:
            if not self.timer.done(now):
                return Outcome.BUSY
            self._enter(HomePhase.SEEK, now)
        return self._seek(now, home)

    def _back_off(self, now: float, home: bool) -> Outcome:
        if not home:
            self.axis.stop()
            self._enter(HomePhase.DWELL, now)
            return Outcome.BUSY
        if self.timer.expired(now):
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch did not open within {self.cfg.backoff_timeout_s:g} s"
                " while backing off (stuck closed or drive not moving)",
            )
        self.axis.rotate_one(Direction.CCW)
        return Outcome.BUSY

    def _seek(self, now: float, home: bool) -> Outcome:
        if home:
            self.axis.stop()
            return Outcome.DONE
        if self.timer.expired(now):
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s"
                " while homing (stuck open or drive not moving)",
            )
        self.axis.rotate_one(Direction.CW)
        return Outcome.BUSY


class RotateRevolutions(AxisController[RotateAxis, RotateSection]):
    """Turn N whole revolutions: each ends on the next closing edge of the home switch."""

    axis_name = "rotate"

    def __init__(
        self,
        axis: RotateAxis,
        cfg: RotateSection,
        direction: Direction,
        revolutions: int,
        home_arc_deg: float = 0.0,
    ) -> None:
        super().__init__(axis, cfg)
        self.direction = direction
        # The switch closes at 0° turning CW and at the end of its arc turning CCW.
        self.target_deg = 0.0 if direction is Direction.CW else home_arc_deg
        self.total = revolutions
        self.done = 0
        self._left: bool | None = None
        self.timer.limit_s = cfg.revolution_timeout_s

    def update(self, now: float) -> Outcome:
        home = self.axis.is_home()
        if not self.timer.started:
            self.timer.start(now)
            self._left = not home
        if not self._left:
            self._left = not home
        elif home:
            self.done += 1
            self._left = False
            self.timer.start(now)
            if self.done >= self.total:
                self.axis.stop()
                return Outcome.DONE
        if self.timer.expired(now):
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s during"
                f" revolution {self.done + 1} of {self.total}",
            )
        self.axis.rotate_one(self.direction)
        return Outcome.BUSY


class RotateCalibrate(Measurement[RotateAxis, RotateSection]):
    """Home, then time one CW revolution edge to edge, and how long the switch stays closed."""

    axis_name = "rotate"
    target_deg = 0.0

    def __init__(self, axis: RotateAxis, cfg: RotateSection) -> None:
        super().__init__(axis, cfg)
        self.homing: RotateHome | None = RotateHome(axis, cfg)
        self._leave_s: float | None = None
        """When the switch opened, seconds into the measured revolution."""
        self.result: RotateCalibration | None = None

    def update(self, now: float) -> Outcome:
        if self.homing is not None:
            outcome = self._step(self.homing, now)
            if outcome is not Outcome.DONE:
                return outcome
            self.homing = None
            self.timer.start(now, self.cfg.revolution_timeout_s)
            self.axis.rotate_one(Direction.CW)
            return Outcome.BUSY
        home = self.axis.is_home()
        if self._leave_s is None:
            if not home:
                self._leave_s = self.timer.elapsed(now)
        elif home:
            self.axis.stop()
            return self._finish(now)
        if self.timer.expired(now):
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s"
                " while measuring a revolution",
            )
        self.axis.rotate_one(Direction.CW)
        return Outcome.BUSY

    def _finish(self, now: float) -> Outcome:
        assert self._leave_s is not None
        revolution_s = self.timer.elapsed(now)
        nominal_s = 360.0 / self.cfg.nominal_speed_dps
        tol = self.cfg.speed_tolerance
        if not nominal_s * (1 - tol) <= revolution_s <= nominal_s * (1 + tol):
            return self._fail(
                FaultCode.CALIBRATION_IMPLAUSIBLE,
                f"one revolution took {revolution_s:.3f} s; expected {nominal_s:.3f} s"
                f" ± {tol:.0%} from rotate.nominal_speed_dps",
            )
        arc = self._leave_s / revolution_s * 360.0
        self.result = RotateCalibration(revolution_s=revolution_s, home_arc_deg=arc)
        return Outcome.DONE

    def _start_over(self) -> None:
        self.homing, self._leave_s = RotateHome(self.axis, self.cfg), None


# ------------------------------------------------------------------------------------ tilt
class TiltSupervisor:
    """Checks the analog position while the tilt is driven: it must follow, and not jump.

    Following: over each `follow_window_s` the raw value must move at least `follow_min_counts`
    the driven way (either way before calibration tells the sign). Noise: a change between two
    samples larger than the drive can cause is a jump; too many within a second is a fault.
    """

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        self.axis, self.cfg = axis, cfg
        self._window = Timeout(cfg.follow_window_s)
        self._window_raw = 0
        self._last: tuple[float, int] | None = None
        self._jumps: deque[float] = deque()

    def reset(self) -> None:
        self._window.stop()
        self._last = None
        self._jumps.clear()

    def check(self, now: float, direction: TiltDirection) -> Fault | None:
        raw = self.axis.read_raw()
        fault = self._check_noise(now, raw)
        if fault is not None:
            return fault
        if not self._window.started:
            self._window.start(now)
            self._window_raw = raw
            return None
        if not self._window.done(now):
            return None
        moved = raw - self._window_raw
        cal = self.axis.calibration
        if cal is None:
            followed = abs(moved) >= self.cfg.follow_min_counts
        else:
            sign = 1.0 if (direction is TiltDirection.UP) == (cal.gain_counts_per_deg > 0) else -1.0
            followed = moved * sign >= self.cfg.follow_min_counts
        if not followed:
            return Fault(
                code=FaultCode.TILT_NOT_FOLLOWING,
                message=f"tilt position moved {moved:+d} counts in {self._window.elapsed(now):.2f}"
                f" s while driven {direction}; expected at least {self.cfg.follow_min_counts}",
                axis="tilt",
            )
        self._window.start(now)
        self._window_raw = raw
        return None

    def _check_noise(self, now: float, raw: int) -> Fault | None:
        last, self._last = self._last, (now, raw)
        if last is None:
            return None
        dt = max(now - last[0], 0.0)
        cal = self.axis.calibration
        gain = abs(cal.gain_counts_per_deg) if cal else self.cfg.gain_max_counts_per_deg
        possible = 1.5 * self.cfg.nominal_speed_dps * gain * dt + self.cfg.noise_jump_counts
        if abs(raw - last[1]) <= possible:
            return None
        self._jumps.append(now)
        while self._jumps and now - self._jumps[0] > 1.0:
            self._jumps.popleft()
        if len(self._jumps) > self.cfg.noise_max_jumps:
            return Fault(
                code=FaultCode.TILT_SIGNAL_NOISY,
                message=f"tilt position jumped more than the drive can move {len(self._jumps)}"
                " times within 1 s (noisy or broken analog signal)",
                axis="tilt",
            )
        return None


class TiltHome(AxisController[TiltAxis, TiltSection]):
    """Drive down until the tilt home switch closes."""

    axis_name = "tilt"
    target_deg = 0.0

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        super().__init__(axis, cfg)
        self.timer.limit_s = cfg.home_timeout_s
        self._sup = TiltSupervisor(axis, cfg)

    def update(self, now: float) -> Outcome:
        if self.axis.is_home():
            self.axis.stop()
            return Outcome.DONE
        if not self.timer.started:
            self.timer.start(now)
        if self.timer.expired(now):
            return self._fail(
                FaultCode.TILT_HOME_TIMEOUT,
                f"tilt home switch not seen within {self.cfg.home_timeout_s:g} s",
            )
        fault = self._sup.check(now, TiltDirection.DOWN)
        if fault is not None:
            return self._fault(fault)
        self.axis.tilt_one(TiltDirection.DOWN)
        return Outcome.BUSY

    def resume(self, now: float) -> None:
        super().resume(now)
        self._sup.reset()


class TiltMove(AxisController[TiltAxis, TiltSection]):
    """Drive to an absolute angle (bang-bang on the relay), then check it settled in tolerance."""

    axis_name = "tilt"
    MAX_CORRECTIONS = 3

    def __init__(self, axis: TiltAxis, cfg: TiltSection, target_deg: float) -> None:
        super().__init__(axis, cfg)
        self.target = self.target_deg = target_deg
        self._sup = TiltSupervisor(axis, cfg)
        self._dir: TiltDirection | None = None
        self._corrections = 0

    def update(self, now: float) -> Outcome:
        pos = self.axis.read_position_degrees()
        if pos is None:
            return self._fail(FaultCode.TILT_TIMEOUT, "tilt is not calibrated")
        err = self.target - pos
        if not self.timer.started:  # armed from the distance left
            travel_s = abs(err) / self.cfg.nominal_speed_dps
            self.timer.start(now, 1.5 * travel_s + self.cfg.move_timeout_margin_s)
        failed = self._stuck(now, pos)
        if failed is not None:
            return failed
        if self._dir is None:  # stopped: settled, or correct an overshoot
            settled = self._settle(err)
            if settled is not None:
                return settled
        return self._drive(now, err)

    def _stuck(self, now: float, pos: float) -> Outcome | None:
        """Too slow, or the home switch still closed well above home: FAULT."""
        if self.timer.expired(now):
            return self._fail(
                FaultCode.TILT_TIMEOUT,
                f"tilt did not reach {self.target:g}° within {self.timer.limit_s:.1f} s"
                f" (at {pos:.1f}°)",
            )
        if self.axis.is_home() and pos > self.cfg.tolerance_deg * 3:
            return self._fail(
                FaultCode.TILT_HOME_STUCK,
                f"tilt home switch still closed at {pos:.1f}° (stuck closed)",
            )
        return None

    def _settle(self, err: float) -> Outcome | None:
        """Stopped: DONE within tolerance, else the way to correct (None), or FAULT after
        too many corrections."""
        if abs(err) <= self.cfg.tolerance_deg:
            return Outcome.DONE
        self._corrections += 1
        if self._corrections > self.MAX_CORRECTIONS:
            return self._fail(
                FaultCode.TILT_TIMEOUT,
                f"tilt could not settle within ±{self.cfg.tolerance_deg:g}° of {self.target:g}°",
            )
        self._dir = TiltDirection.UP if err > 0 else TiltDirection.DOWN
        self._sup.reset()
        return None

    def _drive(self, now: float, err: float) -> Outcome:
        assert self._dir is not None
        reached = abs(err) <= self.cfg.tolerance_deg / 2 or (
            err <= 0 if self._dir is TiltDirection.UP else err >= 0
        )
        if reached:
            self.axis.stop()
            self._dir = None
            return Outcome.BUSY
        fault = self._sup.check(now, self._dir)
        if fault is not None:
            return self._fault(fault)
        self.axis.tilt_one(self._dir)
        return Outcome.BUSY

    def halt(self) -> None:
        super().halt()
        self._dir = None

    def resume(self, now: float) -> None:
        self.timer.stop()  # re-armed from the distance left at the next update
        self._corrections = 0
        self._sup.reset()


class TiltCalPhase(Enum):
    HOME = auto()
    SAMPLE_HOME = auto()
    """Average the raw value at 0° (the offset)."""
    STROKE = auto()
    """Drive up for `calibration_stroke_s` at the nominal speed."""
    SAMPLE_TOP = auto()
    """Average the raw value at the top (with the stroke: the gain)."""
    RETURN = auto()


class TiltCalibrate(Measurement[TiltAxis, TiltSection]):
    """Home (offset at 0°), a timed stroke up at the nominal speed (gain), then home again."""

    axis_name = "tilt"
    target_deg = 0.0

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        super().__init__(axis, cfg)
        self.phase = TiltCalPhase.HOME
        self.homing: TiltHome | None = TiltHome(axis, cfg)
        self._samples: list[int] = []
        self._raw0 = 0.0
        self._stroke_s = 0.0
        self._sup = TiltSupervisor(axis, cfg)
        self.result: TiltCalibration | None = None
        # Measure uncalibrated; a failed calibration puts the previous one back.
        self._previous, axis.calibration = axis.calibration, None

    def update(self, now: float) -> Outcome:
        outcome = self._measure(now)
        if outcome is Outcome.FAULT and self.result is None:
            self.axis.calibration = self._previous
        return outcome

    def _measure(self, now: float) -> Outcome:
        if self.homing is not None:  # HOME or RETURN
            outcome = self._step(self.homing, now)
            if outcome is not Outcome.DONE:
                return outcome
            if self.phase is TiltCalPhase.RETURN:
                return Outcome.DONE
            self.phase, self.homing, self._samples = TiltCalPhase.SAMPLE_HOME, None, []
        if self.phase is TiltCalPhase.SAMPLE_HOME:
            return self._sample_home(now)
        if self.phase is TiltCalPhase.STROKE:
            return self._stroke(now)
        return self._compute() if self._sample() else Outcome.BUSY  # SAMPLE_TOP

    def _sample_home(self, now: float) -> Outcome:
        if self._sample():
            self._raw0 = sum(self._samples) / len(self._samples)
            self.phase = TiltCalPhase.STROKE
            self.timer.start(now, self.cfg.calibration_stroke_s)
            self._sup.reset()
            self.axis.tilt_one(TiltDirection.UP)
        return Outcome.BUSY

    def _stroke(self, now: float) -> Outcome:
        if self.timer.done(now):
            self.axis.stop()
            self._stroke_s = self.timer.elapsed(now)
            self.phase, self._samples = TiltCalPhase.SAMPLE_TOP, []
            return Outcome.BUSY
        fault = self._sup.check(now, TiltDirection.UP)
        if fault is not None:
            return self._fault(fault)
        self.axis.tilt_one(TiltDirection.UP)
        return Outcome.BUSY

    def _sample(self) -> bool:
        self._samples.append(self.axis.read_raw())
        return len(self._samples) >= self.cfg.calibration_samples

    def _compute(self) -> Outcome:
        raw1 = sum(self._samples) / len(self._samples)
        stroke_deg = self.cfg.nominal_speed_dps * self._stroke_s
        gain = (raw1 - self._raw0) / stroke_deg
        lo, hi = self.cfg.gain_min_counts_per_deg, self.cfg.gain_max_counts_per_deg
        if not lo <= gain <= hi:
            return self._fail(
                FaultCode.CALIBRATION_IMPLAUSIBLE,
                f"tilt gain {gain:.2f} counts/° is outside {lo:g}..{hi:g}"
                " (analog input not wired, frozen, or direction output inverted)",
            )
        if self.axis.is_home():
            return self._fail(
                FaultCode.TILT_HOME_STUCK,
                f"tilt home switch still closed {stroke_deg:.1f}° above home (stuck closed)",
            )
        self.result = TiltCalibration(offset_counts=self._raw0, gain_counts_per_deg=gain)
        self.axis.calibration = self.result
        self.phase, self.homing = TiltCalPhase.RETURN, TiltHome(self.axis, self.cfg)
        return Outcome.BUSY

    def abandon(self) -> None:
        self.halt()
        if self.result is None:
            self.axis.calibration = self._previous

    def _start_over(self) -> None:
        # An interrupted stroke measures nothing: start over from home.
        self.phase, self.homing = TiltCalPhase.HOME, TiltHome(self.axis, self.cfg)


# ------------------------------------------------------------------------------- sequences
class Chain(Controller):
    """Run controllers one after another; the next is built only when the previous is done."""

    def __init__(self, steps: Sequence[Callable[[], Controller]]) -> None:
        super().__init__()
        self._factories = list(steps)
        self.index = 0
        self.current: Controller | None = None

    def update(self, now: float) -> Outcome:
        while self.index < len(self._factories):
            if self.current is None:
                self.current = self._factories[self.index]()
            outcome = self._step(self.current, now)
            if outcome is not Outcome.DONE:
                return outcome
            self.current = None
            self.index += 1
        return Outcome.DONE

    def halt(self) -> None:
        if self.current is not None:
            self.current.halt()

    def abandon(self) -> None:
        if self.current is not None:
            self.current.abandon()

    def resume(self, now: float) -> None:
        if self.current is not None:
            self.current.resume(now)

    def active(self) -> Controller | None:
        """The controller doing the work now (through nested chains), if any."""
        return self.current.active() if self.current is not None else None


class SessionRun(Chain):
    """A session's steps as a chain, with progress for the status record."""

    def __init__(
        self, session: Session, devices: Devices, config: MachineConfig, home_arc_deg: float = 0.0
    ) -> None:
        tilt, rotate = devices.tilt, devices.rotate

        def make(step: TiltStep | RotateStep) -> Callable[[], Controller]:
            if isinstance(step, TiltStep):
                return lambda: TiltMove(tilt, config.tilt, step.degrees)
            return lambda: RotateRevolutions(
                rotate, config.rotate, step.direction, step.revolutions, home_arc_deg
            )

        super().__init__([make(s) for s in session.steps])
        self.session = session

    def revolutions_done(self) -> int:
        steps = self.session.steps
        done = sum(s.revolutions for s in steps[: self.index] if isinstance(s, RotateStep))
        if isinstance(self.current, RotateRevolutions):
            done += self.current.done
        return done

    def progress(self) -> SessionProgress:
        steps = self.session.steps
        done = self.revolutions_done()
        total = sum(s.revolutions for s in steps if isinstance(s, RotateStep))
        step = steps[self.index] if self.index < len(steps) else None
        target = next(
            (s.degrees for s in reversed(steps[: self.index + 1]) if isinstance(s, TiltStep)),
            None,
        )
        return SessionProgress(
            name=self.session.name,
            step_index=self.index,
            step_count=len(steps),
            step_kind=step.kind if step is not None else None,
            revolutions_done=done,
            revolutions_total=total,
            tilt_target_deg=target,
        )
