"""Witnesses: the machine's own evidence against the tilt's calibration, every time it has some.

A calibration (raw counts = offset + gain × degrees) is a claim. The seed's IO holds two
witnesses that need no calibration: the home switch closes at 0° (each time the tilt comes down
through it, the analog there must read the offset) and the relay drive has one speed (over a
stroke the analog's counts per second, over the nominal speed, are the gain). `GainWitness` fits
every stroke's samples with a least-squares line, so a busy host's stalls thin the samples out
instead of bending the measure; `ZeroWitness` latches the switch's closing edge on the way down;
`judge_entered` weighs a hand-entered calibration against both after its verification stroke.
Each disagreement is a `Fault` that names its witness and the figure (docs/homing.md).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from ride_machine.schema.status import Fault, FaultCode
from ride_machine.service.config.axes import TiltSection

from .devices import TiltCalibration, TiltDirection

SIGNIFICANCE = 5.0
"""A disagreement must exceed the tolerance by this many standard errors of the fit: noise and
a late sample widen the judgment of that stroke only, never the configured tolerance."""
MIN_SAMPLES = 5


def half_travel(speed_dps: float, before: float | None, after: float) -> float:
    """Half the travel at `speed_dps` between two scans (infinite without the first)."""
    return math.inf if before is None else speed_dps * (after - before) / 2


def line(samples: Sequence[tuple[float, int]]) -> tuple[float, float, float]:
    """The least-squares line through `samples` (time, raw), taken while the drive ran at one
    speed: (mean time, mean raw, slope in counts/s; 0 when all are at one time)."""
    n = len(samples)
    mean_t = sum(s[0] for s in samples) / n
    mean_r = sum(s[1] for s in samples) / n
    var = sum((s[0] - mean_t) ** 2 for s in samples)
    if var == 0.0:
        return mean_t, mean_r, 0.0
    return mean_t, mean_r, sum((s[0] - mean_t) * (s[1] - mean_r) for s in samples) / var


def raw_at(samples: Sequence[tuple[float, int]], t: float) -> float:
    """The analog value at `t` on the line through `samples` (one sample: its value)."""
    mean_t, mean_r, slope = line(samples)
    return mean_r + slope * (t - mean_t)


def reach_deg(cfg: TiltSection) -> float:
    """The farthest a session may take the tilt from 0°: where a gain error shows most."""
    return max(abs(cfg.min_deg), abs(cfg.max_deg), 1.0)


class StrokeFit:
    """A running least-squares line through (time, raw) samples of one stroke."""

    __slots__ = ("_sr", "_srr", "_st", "_str", "_stt", "_t0", "n")

    def __init__(self) -> None:
        self.n = 0
        self._t0 = 0.0
        self._st = self._sr = self._stt = self._str = self._srr = 0.0

    def add(self, t: float, raw: float) -> None:
        if self.n == 0:
            self._t0 = t
        dt = t - self._t0
        self.n += 1
        self._st += dt
        self._sr += raw
        self._stt += dt * dt
        self._str += dt * raw
        self._srr += raw * raw

    @property
    def span_s(self) -> float:
        """From the first sample to the mean time's mirror: the stroke's length so far."""
        return 0.0 if self.n < 2 else 2.0 * (self._st / self.n)

    def _sxx(self) -> float:
        return self._stt - self._st * self._st / self.n

    def slope(self) -> float:
        """Counts per second (0 before two samples at different times)."""
        sxx = self._sxx() if self.n >= 2 else 0.0
        if sxx <= 0.0:
            return 0.0
        return (self._str - self._st * self._sr / self.n) / sxx

    def slope_error(self) -> float:
        """The standard error of `slope` from the residuals (inf before three samples)."""
        if self.n < 3:
            return math.inf
        sxx = self._sxx()
        if sxx <= 0.0:
            return math.inf
        sxy = self._str - self._st * self._sr / self.n
        syy = self._srr - self._sr * self._sr / self.n
        residual = max(syy - sxy * sxy / sxx, 0.0)
        return math.sqrt(residual / (self.n - 2) / sxx)


class GainWitness:
    """The drive's one speed as a witness of the gain: while the tilt is driven, its analog's
    counts per second over the whole stroke (from its first movement) against what the
    calibration's gain says at the nominal speed. Judged once the stroke is a speed window
    long; a disagreement beyond `tilt.gain_tolerance_deg` at the range's far end (as a
    fraction of `reach_deg`), by more than `SIGNIFICANCE` standard errors, is a fault."""

    def __init__(self, cfg: TiltSection) -> None:
        self.cfg = cfg
        self.fit = StrokeFit()
        self._start: int | None = None
        self._pending: deque[tuple[float, int]] = deque()
        self.delay_s = 2.0 * cfg.speed_window_s
        """A sample joins the fit this long after it was taken: by then the follow checks
        (`TiltSupervisor`, within 1.5 speed windows) have said whether the drive stopped
        there (an end stop, a seized gearbox), which is theirs to name, not a gain."""

    def reset(self) -> None:
        """A new stroke (the drive stopped, reversed, paused or started)."""
        self.fit = StrokeFit()
        self._start = None
        self._pending.clear()

    def sample(self, now: float, raw: int) -> None:
        """One scan of the stroke, taken with the drive on."""
        pending = self._pending
        pending.append((now, raw))
        while now - pending[0][0] >= self.delay_s:
            self._add(*pending.popleft())

    def _add(self, t: float, raw: int) -> None:
        """The fit starts at the first sample that moved: the relay reaches a world stepped
        on its own (a process image) up to a step late, and the stroke's speed is judged,
        not its start."""
        if self._start is None:
            self._start = raw
        elif self.fit.n or raw != self._start:
            self.fit.add(t, raw)

    def judge(self, cal: TiltCalibration | None, direction: TiltDirection) -> Fault | None:
        """The fault when the stroke so far disagrees with `cal`; None while it agrees, too
        short to tell, or without a calibration to judge."""
        fit, cfg = self.fit, self.cfg
        if cal is None or fit.n < MIN_SAMPLES or fit.span_s < cfg.speed_window_s:
            return None
        sign = 1.0 if direction is TiltDirection.UP else -1.0
        expected = sign * cal.gain_counts_per_deg * cfg.nominal_speed_dps
        ratio = fit.slope() / expected
        margin = SIGNIFICANCE * fit.slope_error() / abs(expected)
        limit = cfg.gain_tolerance_deg / reach_deg(cfg)
        if abs(ratio - 1.0) <= limit + margin:
            return None
        measured = abs(fit.slope()) / cfg.nominal_speed_dps
        reach, off = reach_deg(cfg), ratio - 1.0
        return Fault(
            code=FaultCode.TILT_GAIN_MISMATCH,
            message=f"the drive's speed witness disagrees with the tilt's gain: over"
            f" {fit.span_s:.2f} s driven {direction} the analog moved"
            f" {abs(fit.slope()):.0f} counts/s, which at the nominal"
            f" {cfg.nominal_speed_dps:g}°/s is {measured:.2f} counts/°; the calibration says"
            f" {cal.gain_counts_per_deg:g} ({off:+.1%}, {abs(off) * reach:.2f}° at {reach:g}°;"
            f" tolerance {cfg.gain_tolerance_deg:g}°): a wrong or stale"
            " calibration, a sensor or coupling that slipped, or a drive off its nominal speed;"
            " calibrate the tilt",
            axis="tilt",
        )


@dataclass(frozen=True, slots=True)
class Pass:
    """The tilt came down through its home switch: the analog where it closed."""

    raw: float
    half_deg: float
    """Half the travel between the scans either side of the edge (how sure the latch is)."""


class ZeroWitness:
    """The home switch as a witness of the offset, on every pass down through it outside
    Home (a session's move toward 0°): the analog at the closing edge, on the line through
    the last speed window of samples, must read 0° by the calibration, within
    `tilt.home_tolerance_deg` (Home's own check) plus how unsure the latch is."""

    def __init__(self, cfg: TiltSection) -> None:
        self.cfg = cfg
        self._samples: deque[tuple[float, int]] = deque()

    def reset(self) -> None:
        self._samples.clear()

    def down(self, now: float, raw: int, home: bool, cal: TiltCalibration | None) -> Fault | None:
        """One scan while driven down: the fault when the switch just closed off the zero."""
        samples = self._samples
        if not home:
            samples.append((now, raw))
            while now - samples[0][0] > self.cfg.speed_window_s:
                samples.popleft()
            return None
        if not samples or cal is None:
            samples.clear()
            return None
        edge = latch_pass(list(samples), now, raw, self.cfg.nominal_speed_dps)
        samples.clear()
        deg = (edge.raw - cal.offset_counts) / cal.gain_counts_per_deg
        if abs(deg) <= self.cfg.home_tolerance_deg + edge.half_deg:
            return None
        return off_zero(deg, edge.raw, cal, self.cfg.home_tolerance_deg, "closed on the way down")


def latch_pass(samples: list[tuple[float, int]], now: float, raw: int, speed_dps: float) -> Pass:
    """The closing edge between the last open scan in `samples` and the closed one at `now`."""
    before = samples[-1][0]
    mid = (before + now) / 2
    return Pass(raw_at([*samples, (now, raw)], mid), half_travel(speed_dps, before, now))


def off_zero(deg: float, raw: float, cal: TiltCalibration, tol: float, event: str) -> Fault:
    """The zero witness's disagreement: the switch `event` ("closed at Home", ...) where the
    analog, read through `cal`, says `deg`."""
    return Fault(
        code=FaultCode.HOME_OFF_ZERO,
        message=f"the home switch witness disagrees with the tilt's offset: the switch {event}"
        f" at {deg:+.2f}° by the calibration (raw {raw:.1f}, offset {cal.offset_counts:g});"
        f" it closes at 0° (tolerance ±{tol:g}°): a wrong or stale calibration, a sensor or"
        " switch that moved; calibrate the tilt",
        axis="tilt",
    )


def judge_entered(
    cal: TiltCalibration, zero_raw: float, gain: float, cfg: TiltSection
) -> Fault | None:
    """A hand-entered calibration against its verification: the zero latched (the mean of two
    passes down through the switch) and the gain of a whole stroke. The position error they
    imply, e_zero + (gain / entered gain - 1) x degrees, is largest at an end of the range;
    beyond `tilt.verify_tolerance_deg` there, the witness that disagrees most is named."""
    zero_deg = (zero_raw - cal.offset_counts) / cal.gain_counts_per_deg
    slip = gain / cal.gain_counts_per_deg - 1.0
    worst = max(abs(zero_deg + slip * cfg.min_deg), abs(zero_deg + slip * cfg.max_deg))
    tol = cfg.verify_tolerance_deg
    if worst <= tol:
        return None
    figures = (
        f"the home switch closes at {zero_raw:.1f} counts, {zero_deg:+.2f}° by the offset"
        f" {cal.offset_counts:g}; a stroke at the nominal {cfg.nominal_speed_dps:g}°/s measures"
        f" {gain:.2f} counts/° against {cal.gain_counts_per_deg:g} entered ({slip:+.1%});"
        f" together {worst:.2f}° off within {cfg.min_deg:g}..{cfg.max_deg:g}° (tolerance"
        f" {tol:g}°): enter the values again, or CalibrateTilt"
    )
    if abs(zero_deg) > tol:
        code, witness = FaultCode.HOME_OFF_ZERO, "the home switch witness"
    else:
        code, witness = FaultCode.TILT_GAIN_MISMATCH, "the drive's speed witness"
    return Fault(
        code=code,
        message=f"the tilt calibration entered by hand is wrong, by {witness}: {figures}",
        axis="tilt",
    )
