"""Plausibility while moving: what the sensors say must agree with what the axis is known to do.

The tilt is relay-driven at a nominal speed, so over each window of drive its analog position,
read through the calibration, must move at that speed (within a tolerance): a 15°/s axis that
"moves" 1.5°/s has a wrong gain or a broken sensor, and motion stops within one window of
travel. The rotate has no sensor between its home edges, so each revolution (closing edge to
closing edge) must take the calibrated time (within a tolerance). docs/homing.md gives the
bounds in degrees.
"""

from __future__ import annotations

from collections import deque

from ride_machine.schema.commands import Direction
from ride_machine.schema.status import Fault, FaultCode
from ride_machine.service.config.axes import RotateSection, TiltSection

from .base import Timeout
from .devices import RotateCalibration, TiltAxis, TiltDirection
from .witness import GainWitness


class TiltSupervisor:
    """Checks the analog position while the tilt is driven: it must follow, at the nominal
    speed, and not jump.

    Following: over each `follow_window_s` the raw value must move at least `follow_min_counts`
    the driven way (up is rising counts, as the commissioned gain is positive). Speed: over each
    `speed_window_s` a calibrated position must move at the nominal speed ± `speed_tolerance`.
    Noise: a change between two samples larger than the drive can cause is a jump; too many
    within a second is a fault. The gain: the whole stroke's speed (`GainWitness`), calibrated.
    """

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        self.axis, self.cfg = axis, cfg
        self._window = Timeout(cfg.follow_window_s)
        self._window_raw = 0
        self._speed = Timeout(cfg.speed_window_s)
        self._speed_raw = 0
        self._half_raw: int | None = None
        self.speed_windows = 0
        """Speed windows judged since the last `reset` (with or without a calibration)."""
        self._last: tuple[float, int] | None = None
        self._jumps: deque[float] = deque()
        self.gain = GainWitness(cfg)
        self._driven: TiltDirection | None = None

    def reset(self) -> None:
        self._window.stop()
        self._speed.stop()
        self.speed_windows = 0
        self._last = None
        self._jumps.clear()
        self.gain.reset()
        self._driven = None

    def drive(self, now: float, direction: TiltDirection) -> Fault | None:
        """One cycle of drive `direction`, checked first: the fault that stops it, or None."""
        fault = self.check(now, direction)
        if fault is None:
            self.axis.drive(direction)
        return fault

    def check(self, now: float, direction: TiltDirection) -> Fault | None:
        if self._driven is not direction:
            self.reset()  # a reversal is a new stroke
            self._driven = direction
        raw = self.axis.read_raw()
        first = self._last is None  # the drive's first cycle since `reset`
        noise = self._check_noise(now, raw)
        if first:
            # The first cycle of a drive writes its relay on only at the cycle's end, which a
            # busy host may delay well past the cycle's time (a container run: 75 ms of a
            # 0.12 s window stood still, "35.3°/s"): the windows start from the next reading,
            # taken with the drive on, as the calibration's stroke takes its samples.
            return noise
        self.gain.sample(now, raw)
        return (
            noise
            or self._check_speed(now, raw, direction)
            or self._check_follow(now, raw, direction)
            or self.gain.judge(self.axis.calibration, direction)
        )

    def _check_follow(self, now: float, raw: int, direction: TiltDirection) -> Fault | None:
        if not self._window.started:
            self._window.start(now)
            self._window_raw = raw
            return None
        if not self._window.done(now):
            return None
        moved = raw - self._window_raw
        if not self._followed(moved, direction):
            return Fault(
                code=FaultCode.TILT_NOT_FOLLOWING,
                message=f"tilt position moved {moved:+d} counts in {self._window.elapsed(now):.2f}"
                f" s while driven {direction}; expected at least {self.cfg.follow_min_counts}",
                axis="tilt",
            )
        self._window.start(now)
        self._window_raw = raw
        return None

    def _followed(self, moved: int, direction: TiltDirection) -> bool:
        # The commissioned gain is positive (`tilt.gain_min_counts_per_deg` > 0): the counts
        # rise going up, calibrated or not, so a direction output wired inverted stops within a
        # window instead of driving the other way until the end stop.
        sign = 1 if direction is TiltDirection.UP else -1
        return moved * sign >= self.cfg.follow_min_counts

    def _check_speed(self, now: float, raw: int, direction: TiltDirection) -> Fault | None:
        """A window's speed by the calibration against the nominal one. A sensor that did not
        follow at all is the follow check's to name (TILT_NOT_FOLLOWING)."""
        if not self._speed.started:
            self._speed.start(now)
            self._speed_raw, self._half_raw = raw, None
            return None
        if not self._speed.done(now):
            if self._half_raw is None and 2 * self._speed.elapsed(now) >= self.cfg.speed_window_s:
                self._half_raw = raw
            return None
        moved, dt = raw - self._speed_raw, self._speed.elapsed(now)
        lately = raw - (self._half_raw if self._half_raw is not None else self._speed_raw)
        self._speed.start(now)
        self._speed_raw, self._half_raw = raw, None
        self.speed_windows += 1
        cal = self.axis.calibration
        if cal is None or not self._followed(moved, direction):
            return None
        if not self._followed(lately, direction):
            return self._stopped(lately, direction)  # a stall or an end stop, not a gain
        cfg = self.cfg
        deg = abs(moved / cal.gain_counts_per_deg)
        speed, nominal, tol = deg / dt, cfg.nominal_speed_dps, cfg.speed_tolerance
        if nominal * (1 - tol) <= speed <= nominal * (1 + tol):
            return None
        cause = (
            "the drive is slow or blocked, the calibration's gain is too large, or the sensor"
            " reads too little"
            if speed < nominal
            else "the calibration's gain is too small, or the sensor jumps"
        )
        return Fault(
            code=FaultCode.TILT_SPEED_IMPLAUSIBLE,
            message=f"tilt moved {deg:.2f}° in {dt:.2f} s by its calibration ({speed:.1f}°/s,"
            f" gain {cal.gain_counts_per_deg:g} counts/°) while driven {direction} at a nominal"
            f" {nominal:g}°/s ± {tol:.0%}: {cause}",
            axis="tilt",
        )

    def _stopped(self, moved: int, direction: TiltDirection) -> Fault:
        return Fault(
            code=FaultCode.TILT_NOT_FOLLOWING,
            message=f"tilt position stopped following: moved {moved:+d} counts in the last"
            f" {self.cfg.speed_window_s / 2:.2f} s while driven {direction}; expected at least"
            f" {self.cfg.follow_min_counts} (drive stalled or blocked, or the sensor stuck)",
            axis="tilt",
        )

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


class RevolutionCheck:
    """Each revolution of a session against the calibrated one: a closing edge must come within
    `revolution_tolerance` of the calibrated revolution time after the one before. Overdue is a
    missed edge, a stuck-open switch or a slow drive; early (edge to edge) is a wrong
    calibration or a switch that closes where it should not."""

    def __init__(self, cfg: RotateSection, cal: RotateCalibration, direction: Direction) -> None:
        self.cfg, self.cal, self.direction = cfg, cal, direction
        self._last: float | None = None
        """The last closing edge, or when the step started or resumed (the overdue check)."""
        self._since: float | None = None
        """The last closing edge, or the step's start: None after a pause (a part revolution)."""
        self._first = False
        self._seen: float | None = None
        """The last cycle that looked (`overdue`), for the gaps between them."""
        self._gap = 0.0
        """The longest gap between two cycles since the last edge (a stalled scan)."""

    def start(self, now: float) -> None:
        """The step starts: its first revolution may be shorter by the home arc (it starts on
        the switch, at either end of it)."""
        self._last = self._since = self._seen = now
        self._first = True
        self._gap = 0.0

    def resume(self, now: float) -> None:
        """After a pause: overdue counts from now; the part revolution is not judged early."""
        self._last, self._since, self._seen, self._gap = now, None, now, 0.0

    def overdue(self, now: float) -> Fault | None:
        """Called every cycle: a revolution that took too long, or None."""
        if self._seen is not None:
            self._gap = max(self._gap, now - self._seen)
        self._seen = now
        late = self.cal.revolution_s * (1 + self.cfg.revolution_tolerance)
        if self._last is None or now - self._last <= late:
            return None
        return Fault(
            code=FaultCode.ROTATE_HOME_TIMEOUT,
            message=f"rotate home switch not seen within {late:.2f} s turning {self.direction}"
            f" (the calibrated revolution {self.cal.revolution_s:.3f} s +"
            f" {self.cfg.revolution_tolerance:.0%}): missed edge, stuck open, or drive slow"
            + self._stalled(),
            axis="rotate",
        )

    def _stalled(self) -> str:
        """What the scan's own longest gap since the last edge says: a gap as long as the home
        switch stays closed can have hidden its edge (a loop watchdog limit that lets a scan
        stall so long: `machine validate` warns of it)."""
        closed_s = self.cal.home_arc_deg / self.cal.speed_dps
        if self._gap < closed_s:
            return ""
        return (
            f"; the scan stalled {self._gap:.3f} s meanwhile, as long as the home switch stays"
            f" closed ({closed_s:.3f} s), so its edge may have passed unseen"
        )

    def edge(self, now: float) -> Fault | None:
        """A closing edge at `now`. Late is judged here too, not only by `overdue` between
        edges: a scan stalled across the moment a revolution became overdue (and across an
        edge it hid) saw no cycle in which to call it so, and counted one revolution for two."""
        last, since, first = self._last, self._since, self._first
        overdue = self.overdue(now)
        stalled = self._stalled()
        self._last = self._since = now
        self._first = False
        self._gap = 0.0
        if overdue is not None and last is not None:
            return overdue.model_copy(
                update={
                    "message": f"a revolution took {now - last:.3f} s turning {self.direction}:"
                    f" longer than the calibrated {self.cal.revolution_s:.3f} s +"
                    f" {self.cfg.revolution_tolerance:.0%}, so a home edge may have passed"
                    f" unseen, or the drive is slow{stalled}"
                }
            )
        revolution = self.cal.revolution_s
        if first:
            revolution -= self.cal.home_arc_deg / self.cal.speed_dps
        if since is None or now - since >= revolution * (1 - self.cfg.revolution_tolerance):
            return None
        return Fault(
            code=FaultCode.ROTATE_SPEED_IMPLAUSIBLE,
            message=f"a revolution took {now - since:.3f} s turning {self.direction}; the"
            f" calibration says {self.cal.revolution_s:.3f} s ± {self.cfg.revolution_tolerance:.0%}"
            " (wrong calibration, or a home switch that closes where it should not)",
            axis="rotate",
        )
