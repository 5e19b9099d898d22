"""Non-blocking controllers: each `update(now)` looks at the inputs and sets the outputs once.

They read no clock (time comes in as `now`), touch no IO beyond the devices, and never block.
A controller ends `DONE` or `FAULT` (with a `Fault` saying why); `halt()` drops its outputs for a
pause or an E-stop and `resume(now)` restarts its timeout windows, so paused time never counts.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from enum import Enum, auto

from schema.commands import Direction, RotateStep, Session, TiltStep
from schema.status import Fault, FaultCode, SessionProgress
from service.config import RotateSection, TiltSection
from service.devices import (
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

    def _fail(self, code: FaultCode, message: str) -> Outcome:
        self.halt()
        self.fault = Fault(code=code, message=message, axis=self.axis_name or None)
        return Outcome.FAULT


# ---------------------------------------------------------------------------------- rotate
class RotateHome(Controller):
    """Back off the switch if on it (CCW), dwell, then seek its closing edge CW."""

    axis_name = "rotate"
    target_deg = 0.0

    def __init__(self, axis: RotateAxis, cfg: RotateSection) -> None:
        super().__init__()
        self.axis, self.cfg = axis, cfg
        self._phase = "start"
        self._t0 = 0.0

    def update(self, now: float) -> Outcome:
        home = self.axis.is_home()
        if self._phase == "start":
            self._phase, self._t0 = ("backoff" if home else "seek"), now
        if self._phase == "backoff":
            if home:
                if now - self._t0 > self.cfg.backoff_timeout_s:
                    return self._fail(
                        FaultCode.ROTATE_HOME_TIMEOUT,
                        f"rotate home switch did not open within {self.cfg.backoff_timeout_s:g} s"
                        " while backing off (stuck closed or drive not moving)",
                    )
                self.axis.rotate_one(Direction.CCW)
                return Outcome.BUSY
            self.axis.stop()
            self._phase, self._t0 = "dwell", now
            return Outcome.BUSY
        if self._phase == "dwell":
            if now - self._t0 < REVERSE_DWELL_S:
                return Outcome.BUSY
            self._phase, self._t0 = "seek", now
        if home:
            self.axis.stop()
            return Outcome.DONE
        if now - self._t0 > self.cfg.revolution_timeout_s:
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s"
                " while homing (stuck open or drive not moving)",
            )
        self.axis.rotate_one(Direction.CW)
        return Outcome.BUSY

    def halt(self) -> None:
        self.axis.stop()

    def resume(self, now: float) -> None:
        self._t0 = now


class RotateRevolutions(Controller):
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
        super().__init__()
        self.axis, self.cfg = axis, cfg
        self.direction = direction
        # The switch closes at 0° turning CW and at the end of its arc turning CCW.
        self.target_deg = 0.0 if direction is Direction.CW else home_arc_deg
        self.total = revolutions
        self.done = 0
        self._left: bool | None = None
        self._t0: float | None = None

    def update(self, now: float) -> Outcome:
        home = self.axis.is_home()
        if self._t0 is None:
            self._t0 = now
            self._left = not home
        if not self._left:
            self._left = not home
        elif home:
            self.done += 1
            self._left, self._t0 = False, now
            if self.done >= self.total:
                self.axis.stop()
                return Outcome.DONE
        if now - self._t0 > self.cfg.revolution_timeout_s:
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s during"
                f" revolution {self.done + 1} of {self.total}",
            )
        self.axis.rotate_one(self.direction)
        return Outcome.BUSY

    def halt(self) -> None:
        self.axis.stop()

    def resume(self, now: float) -> None:
        if self._t0 is not None:
            self._t0 = now


class RotateCalibrate(Controller):
    """Home, then time one CW revolution edge to edge, and how long the switch stays closed."""

    axis_name = "rotate"
    target_deg = 0.0

    def __init__(self, axis: RotateAxis, cfg: RotateSection) -> None:
        super().__init__()
        self.axis, self.cfg = axis, cfg
        self._home = RotateHome(axis, cfg)
        self._phase = "home"
        self._t_start = 0.0
        self._t_leave: float | None = None
        self.result: RotateCalibration | None = None

    def update(self, now: float) -> Outcome:
        if self._phase == "home":
            outcome = self._home.update(now)
            if outcome is Outcome.FAULT:
                self.fault = self._home.fault
                return outcome
            if outcome is Outcome.DONE:
                self._phase, self._t_start = "measure", now
                self.axis.rotate_one(Direction.CW)
            return Outcome.BUSY
        home = self.axis.is_home()
        if self._t_leave is None:
            if not home:
                self._t_leave = now
        elif home:
            self.axis.stop()
            return self._finish(now)
        if now - self._t_start > self.cfg.revolution_timeout_s:
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s"
                " while measuring a revolution",
            )
        self.axis.rotate_one(Direction.CW)
        return Outcome.BUSY

    def _finish(self, now: float) -> Outcome:
        assert self._t_leave is not None
        revolution_s = now - self._t_start
        nominal_s = 360.0 / self.cfg.nominal_speed_dps
        tol = self.cfg.speed_tolerance
        if not nominal_s * (1 - tol) <= revolution_s <= nominal_s * (1 + tol):
            return self._fail(
                FaultCode.CALIBRATION_IMPLAUSIBLE,
                f"one revolution took {revolution_s:.3f} s; expected {nominal_s:.3f} s"
                f" ± {tol:.0%} from rotate.nominal_speed_dps",
            )
        arc = (self._t_leave - self._t_start) / revolution_s * 360.0
        self.result = RotateCalibration(revolution_s=revolution_s, home_arc_deg=arc)
        return Outcome.DONE

    def halt(self) -> None:
        self.axis.stop()

    def resume(self, now: float) -> None:
        if self._phase == "home":
            self._home.resume(now)
        else:
            # A paused measurement is worthless: re-home and measure again.
            self._home = RotateHome(self.axis, self.cfg)
            self._phase, self._t_leave = "home", None


# ------------------------------------------------------------------------------------ tilt
class TiltSupervisor:
    """Checks the analog position while the tilt is driven: it must follow, and not jump.

    Following: over each `follow_window_s` the raw value must move at least `follow_min_counts`
    the driven way (either way before calibration tells the sign). Noise: a change between two
    samples larger than the drive can cause is a jump; too many within a second is a fault.
    """

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        self.axis, self.cfg = axis, cfg
        self._window_t: float | None = None
        self._window_raw = 0
        self._last: tuple[float, int] | None = None
        self._jumps: deque[float] = deque()

    def reset(self) -> None:
        self._window_t = None
        self._last = None
        self._jumps.clear()

    def check(self, now: float, direction: TiltDirection) -> Fault | None:
        raw = self.axis.read_raw()
        fault = self._check_noise(now, raw)
        if fault is not None:
            return fault
        if self._window_t is None:
            self._window_t, self._window_raw = now, raw
            return None
        if now - self._window_t < self.cfg.follow_window_s:
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
                message=f"tilt position moved {moved:+d} counts in {now - self._window_t:.2f} s"
                f" while driven {direction}; expected at least {self.cfg.follow_min_counts}",
                axis="tilt",
            )
        self._window_t, self._window_raw = now, raw
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


class TiltHome(Controller):
    """Drive down until the tilt home switch closes."""

    axis_name = "tilt"
    target_deg = 0.0

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        super().__init__()
        self.axis, self.cfg = axis, cfg
        self._t0: float | None = None
        self._sup = TiltSupervisor(axis, cfg)

    def update(self, now: float) -> Outcome:
        if self.axis.is_home():
            self.axis.stop()
            return Outcome.DONE
        if self._t0 is None:
            self._t0 = now
        if now - self._t0 > self.cfg.home_timeout_s:
            return self._fail(
                FaultCode.TILT_HOME_TIMEOUT,
                f"tilt home switch not seen within {self.cfg.home_timeout_s:g} s",
            )
        fault = self._sup.check(now, TiltDirection.DOWN)
        if fault is not None:
            self.halt()
            self.fault = fault
            return Outcome.FAULT
        self.axis.tilt_one(TiltDirection.DOWN)
        return Outcome.BUSY

    def halt(self) -> None:
        self.axis.stop()

    def resume(self, now: float) -> None:
        self._t0 = now
        self._sup.reset()


class TiltMove(Controller):
    """Drive to an absolute angle (bang-bang on the relay), then check it settled in tolerance."""

    axis_name = "tilt"
    MAX_CORRECTIONS = 3

    def __init__(self, axis: TiltAxis, cfg: TiltSection, target_deg: float) -> None:
        super().__init__()
        self.axis, self.cfg = axis, cfg
        self.target = self.target_deg = target_deg
        self._sup = TiltSupervisor(axis, cfg)
        self._t0: float | None = None
        self._timeout = 0.0
        self._dir: TiltDirection | None = None
        self._corrections = 0

    def update(self, now: float) -> Outcome:
        pos = self.axis.read_position_degrees()
        if pos is None:
            return self._fail(FaultCode.TILT_TIMEOUT, "tilt is not calibrated")
        err = self.target - pos
        if self._t0 is None:
            self._arm(now, err)
        assert self._t0 is not None
        if now - self._t0 > self._timeout:
            return self._fail(
                FaultCode.TILT_TIMEOUT,
                f"tilt did not reach {self.target:g}° within {self._timeout:.1f} s (at {pos:.1f}°)",
            )
        if self.axis.is_home() and pos > self.cfg.tolerance_deg * 3:
            return self._fail(
                FaultCode.TILT_HOME_STUCK,
                f"tilt home switch still closed at {pos:.1f}° (stuck closed)",
            )
        if self._dir is None:  # stopped: settled, or correct an overshoot
            if abs(err) <= self.cfg.tolerance_deg:
                return Outcome.DONE
            self._corrections += 1
            if self._corrections > self.MAX_CORRECTIONS:
                return self._fail(
                    FaultCode.TILT_TIMEOUT,
                    f"tilt could not settle within ±{self.cfg.tolerance_deg:g}°"
                    f" of {self.target:g}°",
                )
            self._dir = TiltDirection.UP if err > 0 else TiltDirection.DOWN
            self._sup.reset()
        reached = abs(err) <= self.cfg.tolerance_deg / 2 or (
            err <= 0 if self._dir is TiltDirection.UP else err >= 0
        )
        if reached:
            self.axis.stop()
            self._dir = None
            return Outcome.BUSY
        fault = self._sup.check(now, self._dir)
        if fault is not None:
            self.halt()
            self.fault = fault
            return Outcome.FAULT
        self.axis.tilt_one(self._dir)
        return Outcome.BUSY

    def _arm(self, now: float, err: float) -> None:
        self._t0 = now
        travel_s = abs(err) / self.cfg.nominal_speed_dps
        self._timeout = 1.5 * travel_s + self.cfg.move_timeout_margin_s

    def halt(self) -> None:
        self.axis.stop()
        self._dir = None

    def resume(self, now: float) -> None:
        self._t0 = None
        self._corrections = 0
        self._sup.reset()


class TiltCalibrate(Controller):
    """Home (offset at 0°), a timed stroke up at the nominal speed (gain), then home again."""

    axis_name = "tilt"
    target_deg = 0.0

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        super().__init__()
        self.axis, self.cfg = axis, cfg
        self._phase = "home"
        self._sub: Controller = TiltHome(axis, cfg)
        self._samples: list[int] = []
        self._raw0 = 0.0
        self._t_on = 0.0
        self._t_off = 0.0
        self._sup = TiltSupervisor(axis, cfg)
        self.result: TiltCalibration | None = None
        # Measure uncalibrated; a failed calibration puts the previous one back.
        self._previous, axis.calibration = axis.calibration, None

    def update(self, now: float) -> Outcome:
        outcome = self._step(now)
        if outcome is Outcome.FAULT and self.result is None:
            self.axis.calibration = self._previous
        return outcome

    def _step(self, now: float) -> Outcome:
        if self._phase in ("home", "return"):
            outcome = self._sub.update(now)
            if outcome is Outcome.FAULT:
                self.fault = self._sub.fault
                return outcome
            if outcome is Outcome.BUSY:
                return outcome
            if self._phase == "return":
                return Outcome.DONE
            self._phase, self._samples = "sample0", []
        if self._phase == "sample0":
            if self._sample():
                self._raw0 = sum(self._samples) / len(self._samples)
                self._phase, self._t_on = "stroke", now
                self._sup.reset()
                self.axis.tilt_one(TiltDirection.UP)
            return Outcome.BUSY
        if self._phase == "stroke":
            if now - self._t_on >= self.cfg.calibration_stroke_s:
                self.axis.stop()
                self._phase, self._t_off, self._samples = "sample1", now, []
                return Outcome.BUSY
            fault = self._sup.check(now, TiltDirection.UP)
            if fault is not None:
                self.halt()
                self.fault = fault
                return Outcome.FAULT
            self.axis.tilt_one(TiltDirection.UP)
            return Outcome.BUSY
        # sample1
        if not self._sample():
            return Outcome.BUSY
        return self._compute()

    def _sample(self) -> bool:
        self._samples.append(self.axis.read_raw())
        return len(self._samples) >= self.cfg.calibration_samples

    def _compute(self) -> Outcome:
        raw1 = sum(self._samples) / len(self._samples)
        stroke_deg = self.cfg.nominal_speed_dps * (self._t_off - self._t_on)
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
        self._phase, self._sub = "return", TiltHome(self.axis, self.cfg)
        return Outcome.BUSY

    def halt(self) -> None:
        self.axis.stop()

    def abandon(self) -> None:
        self.halt()
        if self.result is None:
            self.axis.calibration = self._previous

    def resume(self, now: float) -> None:
        if self._phase in ("home", "return"):
            self._sub.resume(now)
            return
        # An interrupted stroke measures nothing: start over from home.
        self._phase, self._sub = "home", TiltHome(self.axis, self.cfg)


# ------------------------------------------------------------------------------- sequences
class Chain(Controller):
    """Run controllers one after another; the next is built only when the previous is done."""

    def __init__(self, steps: Sequence[Callable[[], Controller]]) -> None:
        super().__init__()
        self._factories = list(steps)
        self.index = 0
        self.current: Controller | None = None
        self.finished: list[Controller] = []

    def update(self, now: float) -> Outcome:
        while self.index < len(self._factories):
            if self.current is None:
                self.current = self._factories[self.index]()
            outcome = self.current.update(now)
            if outcome is Outcome.FAULT:
                self.fault = self.current.fault
                return outcome
            if outcome is Outcome.BUSY:
                return outcome
            self.finished.append(self.current)
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
        current = self.current
        return current.active() if isinstance(current, Chain) else current


class SessionRun(Chain):
    """A session's steps as a chain, with progress for the status record."""

    def __init__(
        self,
        session: Session,
        tilt: TiltAxis,
        rotate: RotateAxis,
        tilt_cfg: TiltSection,
        rotate_cfg: RotateSection,
        home_arc_deg: float = 0.0,
    ) -> None:
        def make(step: TiltStep | RotateStep) -> Callable[[], Controller]:
            if isinstance(step, TiltStep):
                return lambda: TiltMove(tilt, tilt_cfg, step.degrees)
            return lambda: RotateRevolutions(
                rotate, rotate_cfg, step.direction, step.revolutions, home_arc_deg
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
