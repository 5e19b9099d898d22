"""Homing: each axis approaches its home switch's closing edge from one side and latches it.

As LinuxCNC homes (search, back off, latch, final move) within relay drives that have one speed:
a switch found closed is backed off until it opens and `runup_s` beyond (never latched where it
was found), the drive rests (`REVERSE_DWELL_S`), then seeks the closing edge — the tilt going
down, the rotate turning CW. The edge is latched from the scans either side of it: it happened
between the last scan that saw the switch open and the first that saw it closed, so the latch is
their midpoint, sure to half the travel between them. A latch less sure than the axis's
`latch_tolerance_deg` (a late scan, a stalled host) is approached again, `latch_attempts` times
at most, then `HOME_EDGE_UNCERTAIN`. The tilt's latch is the analog value at that midpoint, on
the least-squares line through the approach's samples (the drive runs at one speed, so noise
averages out). An approach ends only when a scan after its stop was written still reads the
switch closed (`OnSwitch`); else it ran past, and approaches again. docs/homing.md has the
sequences, the tolerances and what a late scan costs.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum, auto

from ride_machine.schema.commands import Direction
from ride_machine.schema.status import Fault, FaultCode
from ride_machine.service.config.axes import RotateSection, TiltSection

from .base import (
    REVERSE_DWELL_S,
    AxisController,
    AxisT,
    CfgT,
    Step,
)
from .devices import RotateAxis, TiltAxis, TiltDirection
from .plausibility import TiltSupervisor
from .witness import half_travel, off_zero, raw_at


@dataclass(frozen=True, slots=True)
class Latch:
    """One switch edge, from the scans either side of it."""

    before: float
    """When the last scan saw the switch as it was."""
    after: float
    """When the first scan saw it changed."""
    half_deg: float
    """Half the travel between the two scans: how far the edge may lie from the midpoint."""
    raw: float | None = None
    """The tilt: the analog value at the midpoint (on the line through the approach)."""

    @property
    def at(self) -> float:
        """When the edge most likely happened: midway between the two scans."""
        return (self.before + self.after) / 2

    @property
    def gap_ms(self) -> float:
        return (self.after - self.before) * 1000.0


@dataclass(slots=True)
class OnSwitch:
    """A stop on the home switch's closing edge, checked: is the axis still on the switch?

    The stop is written at the end of the scan that read the edge; a scan preempted before
    that write (a loaded host) or a seat that coasts runs on meanwhile, and the rotate, at the
    integration tests' 720°/s, leaves its 10° arc in 14 ms: homed by the latch but not resting
    on the switch that Start asks for (run 61: Home DONE, then Start refused `NOT_HOME`). A
    scan after the write that reads the switch closed says it is; one that reads it open is a
    contact bouncing or an axis past the switch, told apart by waiting out the relay's rest
    (`REVERSE_DWELL_S`), due before any reversal anyway."""

    since: float
    """The scan that wrote the stop."""

    def step(self, now: float, home: bool) -> Step | None:
        """DONE: on the switch; BUSY: not known yet (read it again); None: it ran past."""
        if home:
            return Step.DONE
        return Step.BUSY if now - self.since < REVERSE_DWELL_S else None


class Phase(Enum):
    START = auto()
    REST = auto()
    """Relay off before the first drive (the axis may have just been driven the other way)."""
    BACKOFF = auto()
    """Driven away from the switch until it opens."""
    RUNUP = auto()
    """On away for `runup_s`: clear of the hysteresis, room to reach speed."""
    DWELL = auto()
    """Relay off before reversing."""
    SEEK = auto()
    """Driven toward the closing edge, from the defined side."""
    STOPPED = auto()
    """Stopped on the latched edge, until a later scan reads the switch still closed."""


class EdgeApproach(AxisController[AxisT, CfgT]):
    """Back off the home switch if closed (until open, then `runup_s` more), dwell, seek its
    closing edge from the defined side, and latch it; a latch too unsure is approached again."""

    target_deg = 0.0

    def _setup(self, rest_s: float) -> None:
        """The approach's state (called by the axis's `__init__` after the base's)."""
        self.phase = Phase.START
        self.behind = False
        """The switch lies behind, the way the axis backs off: the axis ran on past it (a last
        edge seen as the rotate halted or across a stalled scan). The first back-off then goes
        through the switch, not a whole revolution round to it."""
        self.attempts = 0
        """Latches refused so far."""
        self.latch: Latch | None = None
        self._stopped: OnSwitch | None = None
        self.refused: list[str] = []
        """Why each refused latch was refused (for the fault message)."""
        self._limits = {
            Phase.REST: rest_s,
            Phase.BACKOFF: self.cfg.backoff_timeout_s,
            Phase.RUNUP: self.cfg.runup_s,
            Phase.DWELL: REVERSE_DWELL_S,
            Phase.SEEK: self._seek_limit(),
        }

    # -- the axis's part ----------------------------------------------------------------
    def _seek_limit(self) -> float:
        raise NotImplementedError

    def _drive(self, now: float, away: bool) -> Step:
        """Drive away from the switch (back off) or toward it (seek) for one cycle."""
        raise NotImplementedError

    def _moving(self) -> None:
        """A drive phase begins: forget the samples of the one before."""

    def _sample(self, now: float) -> None:
        """A scan of the seek that saw the switch still open."""

    def _latch(self, now: float) -> Latch | None:
        """The edge just seen at `now`, from the samples before it (None: none to go by)."""
        raise NotImplementedError

    def _ran_up(self) -> bool:
        return True

    def _ran_past(self) -> None:
        """Stopped on the edge, the axis was found off the switch after the stop."""

    def _accept(self, latch: Latch) -> Step:
        return Step.DONE

    def _stuck_closed(self, now: float) -> Fault:
        raise NotImplementedError

    def _not_found(self) -> Fault:
        raise NotImplementedError

    # -- the sequence -------------------------------------------------------------------
    def _enter(self, phase: Phase, now: float) -> None:
        self.phase = phase
        self.timer.start(now, self._limits[phase])
        if phase in (Phase.BACKOFF, Phase.SEEK):
            self._moving()

    def update(self, now: float) -> Step:
        home = self.axis.is_home()
        if self.phase is Phase.STOPPED:
            return self._on_switch(now, home)
        if self.phase is Phase.START:
            if self._limits[Phase.REST]:
                self._enter(Phase.REST, now)
            else:
                self._enter(Phase.BACKOFF if home or self.behind else Phase.SEEK, now)
        if self.phase in (Phase.REST, Phase.DWELL):
            if not self.timer.done(now):
                return Step.BUSY
            self._enter(Phase.BACKOFF if home or self.behind else Phase.SEEK, now)
        if self.phase is Phase.BACKOFF:
            if home:
                self.behind = False  # reached: now off it as from any closed switch
            if not home and not self.behind:
                self._enter(Phase.RUNUP, now)
            elif self.timer.expired(now):
                return self._fault(self._not_found() if self.behind else self._stuck_closed(now))
        if self.phase is Phase.RUNUP:
            return self._run_up(now, home)
        if self.phase is Phase.SEEK:
            return self._seek(now, home)
        return self._drive(now, away=True)

    def _run_up(self, now: float, home: bool) -> Step:
        if not self.timer.done(now):
            return self._drive(now, away=True)
        if home:  # closed again after opening, well past its hysteresis
            return self._fault(self._stuck_closed(now))
        self.axis.stop()
        self._enter(Phase.DWELL, now)
        return Step.BUSY

    def _seek(self, now: float, home: bool) -> Step:
        if not home:
            if self.timer.expired(now):
                return self._fault(self._not_found())
            self._sample(now)
            return self._drive(now, away=False)
        self.axis.stop()
        latch = self._latch(now)
        problem = self._problem(latch)
        if problem is None:
            self.latch, self._stopped = latch, OnSwitch(now)
            self.phase = Phase.STOPPED
            return Step.BUSY
        return self._refuse(problem, now)

    def _on_switch(self, now: float, home: bool) -> Step:
        assert self._stopped is not None and self.latch is not None
        step = self._stopped.step(now, home)
        if step is Step.DONE:
            return self._accept(self.latch)
        if step is not None:
            return step
        self._ran_past()
        return self._refuse(
            f"off the switch {REVERSE_DWELL_S:g} s after the stop (a stop written late by a"
            " stalled scan, or a coasting axis, ran past it)",
            now,
        )

    def _refuse(self, problem: str, now: float) -> Step:
        self.refused.append(problem)
        self.attempts += 1
        if self.attempts >= self.cfg.latch_attempts:
            return self._fail(
                FaultCode.HOME_EDGE_UNCERTAIN,
                f"{self.axis_name} home edge not latched within"
                f" ±{self.cfg.latch_tolerance_deg:g}° in {self.attempts} approaches:"
                f" {'; '.join(self.refused)} (a loaded host stalling the scan, or a bouncing"
                " switch)",
            )
        self._enter(Phase.DWELL, now)  # then back off (the switch is closed) and approach again
        return Step.BUSY

    def _problem(self, latch: Latch | None) -> str | None:
        """Why `latch` cannot be trusted; None: it can."""
        if latch is None:
            return "closed at the first scan of the approach"
        if latch.half_deg > self.cfg.latch_tolerance_deg:
            return f"scans {latch.gap_ms:.0f} ms apart at the edge (±{latch.half_deg:.2f}°)"
        if not self._ran_up():
            return "reached before the speed was checked (started too close)"
        return None

    def halt(self) -> None:
        self.axis.stop()

    def resume(self, now: float) -> None:
        """After a pause: from the start (rest, then back off or seek), samples forgotten;
        stopped on a latched edge, the next scan reads whether it is still on the switch."""
        if self.phase is Phase.STOPPED:
            return
        self.phase = Phase.START
        self._limits[Phase.REST] = REVERSE_DWELL_S


# ------------------------------------------------------------------------------------ tilt
class TiltApproach(EdgeApproach[TiltAxis, TiltSection]):
    """The tilt: backs off up, seeks down; the latch is the analog value at the edge on the line
    through the last `speed_window_s` of samples, supervised (follow, speed, noise) throughout."""

    axis_name = "tilt"

    def __init__(self, axis: TiltAxis, cfg: TiltSection, rest_s: float = 0.0) -> None:
        super().__init__(axis, cfg)
        self._setup(rest_s)
        self._sup = TiltSupervisor(axis, cfg)
        self._samples: deque[tuple[float, int]] = deque()

    def _seek_limit(self) -> float:
        return self.cfg.home_timeout_s

    def _drive(self, now: float, away: bool) -> Step:
        fault = self._sup.drive(now, TiltDirection.UP if away else TiltDirection.DOWN)
        return Step.BUSY if fault is None else self._fault(fault)

    def _moving(self) -> None:
        self._sup.reset()
        self._samples.clear()

    def _sample(self, now: float) -> None:
        samples = self._samples
        samples.append((now, self.axis.read_raw()))
        while now - samples[0][0] > self.cfg.speed_window_s:
            samples.popleft()

    def _latch(self, now: float) -> Latch | None:
        if not self._samples:
            return None
        before = self._samples[-1][0]
        mid = (before + now) / 2
        raw = raw_at([*self._samples, (now, self.axis.read_raw())], mid)
        return Latch(before, now, half_travel(self.cfg.nominal_speed_dps, before, now), raw)

    def _ran_up(self) -> bool:
        return self._sup.speed_windows > 0

    def _stuck_closed(self, now: float) -> Fault:
        return Fault(
            code=FaultCode.TILT_HOME_STUCK,
            message=f"tilt home switch still closed after backing off up for"
            f" {self.timer.elapsed(now):.1f} s (stuck closed, or the drive not moving up)",
            axis="tilt",
        )

    def _not_found(self) -> Fault:
        return Fault(
            code=FaultCode.TILT_HOME_TIMEOUT,
            message=f"tilt home switch not seen within {self.cfg.home_timeout_s:g} s",
            axis="tilt",
        )

    def resume(self, now: float) -> None:
        super().resume(now)
        self._moving()


class TiltHome(TiltApproach):
    """Home: the approach, then (calibrated) the edge must lie within `home_tolerance_deg` of the
    calibrated zero."""

    def _accept(self, latch: Latch) -> Step:
        cal = self.axis.calibration
        if cal is None or latch.raw is None:
            return Step.DONE
        deg = (latch.raw - cal.offset_counts) / cal.gain_counts_per_deg
        tol = self.cfg.home_tolerance_deg
        if abs(deg) <= tol:
            return Step.DONE
        return self._fault(off_zero(deg, latch.raw, cal, tol, "closed at Home"))


# ---------------------------------------------------------------------------------- rotate
class RotateHome(EdgeApproach[RotateAxis, RotateSection]):
    """The rotate: backs off CCW, seeks CW; the latch is the midpoint in time, sure to half the
    travel at `speed_dps` (calibrated, else nominal) between the scans either side."""

    axis_name = "rotate"

    def __init__(
        self,
        axis: RotateAxis,
        cfg: RotateSection,
        speed_dps: float | None = None,
        rest_s: float = 0.0,
    ) -> None:
        super().__init__(axis, cfg)
        self._setup(rest_s)
        self.speed = speed_dps or cfg.nominal_speed_dps
        self._last: float | None = None

    def _seek_limit(self) -> float:
        return self.cfg.revolution_timeout_s

    def _drive(self, now: float, away: bool) -> Step:
        self.axis.drive(Direction.CCW if away else Direction.CW)
        return Step.BUSY

    def _moving(self) -> None:
        self._last = None

    def _sample(self, now: float) -> None:
        self._last = now

    def _latch(self, now: float) -> Latch | None:
        before = self._last
        if before is None:
            return None
        return Latch(before, now, half_travel(self.speed, before, now))

    def _ran_past(self) -> None:
        self.behind = True  # on past the arc, CW: back off CCW through it

    def _stuck_closed(self, now: float) -> Fault:
        return Fault(
            code=FaultCode.ROTATE_HOME_TIMEOUT,
            message=f"rotate home switch did not open within {self.cfg.backoff_timeout_s:g} s"
            " while backing off (stuck closed or drive not moving)",
            axis="rotate",
        )

    def _not_found(self) -> Fault:
        return Fault(
            code=FaultCode.ROTATE_HOME_TIMEOUT,
            message=f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s"
            " while homing (stuck open or drive not moving)",
            axis="rotate",
        )

    def resume(self, now: float) -> None:
        super().resume(now)
        self._moving()
