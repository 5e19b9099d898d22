"""The tilt sensor's commissioned scale: the one check of a tilt calibration that no drive speed
can fool. A stroke's gain is its counts per second over the drive's nominal speed, so a drive
10 % fast calibrates 10 % high and every speed witness agrees with it afterwards; the band from
the sensor's datasheet (`tilt.gain_min/max_counts_per_deg`) and the raw value commissioned at
the home switch (`tilt.zero_min/max_counts`) do not move with it (docs/homing.md)."""

from __future__ import annotations

from dataclasses import dataclass

from ride_machine.schema.status import Fault, FaultCode
from ride_machine.service.config.axes import TiltSection


@dataclass(frozen=True)
class ScaleProblem:
    """Which value lies outside the commissioned scale, and why it matters, in words."""

    path: str
    """`/tilt/gain_counts_per_deg` or `/tilt/offset_counts` (a calibration's fields)."""
    message: str


def gain_problem(gain: float, cfg: TiltSection) -> ScaleProblem | None:
    lo, hi = cfg.gain_min_counts_per_deg, cfg.gain_max_counts_per_deg
    return _outside(
        gain,
        lo,
        hi,
        "/tilt/gain_counts_per_deg",
        f"tilt gain {gain:.2f} counts/° is outside the sensor's commissioned {lo:g}..{hi:g}"
        " (tilt.gain_min/max_counts_per_deg): a drive off its nominal speed"
        f" ({cfg.nominal_speed_dps:g}°/s), a slipping or stalling drive, an analog input not"
        " wired or frozen, or a value typed wrong",
    )


def zero_problem(offset: float, cfg: TiltSection) -> ScaleProblem | None:
    lo, hi = cfg.zero_min_counts, cfg.zero_max_counts
    return _outside(
        offset,
        lo,
        hi,
        "/tilt/offset_counts",
        f"tilt zero {offset:.1f} counts is outside the commissioned {lo:g}..{hi:g} at the home"
        " switch (tilt.zero_min/max_counts): the switch moved, the sensor slipped on its shaft,"
        " or a value typed wrong",
    )


def _outside(value: float, lo: float, hi: float, path: str, message: str) -> ScaleProblem | None:
    return None if lo <= value <= hi else ScaleProblem(path, message)


def scale_problem(offset: float, gain: float, cfg: TiltSection) -> ScaleProblem | None:
    """The first of a tilt calibration's values outside the commissioned scale, or None."""
    return gain_problem(gain, cfg) or zero_problem(offset, cfg)


_envelope: tuple[TiltSection, tuple[float, float]] | None = None
"""The last `[tilt]` section asked about and its envelope, replaced as one value: every full
scan cycle asks (`signal_fault`), and the section is a new object only when a parameter
changes."""


def raw_envelope(cfg: TiltSection) -> tuple[float, float]:
    """The raw values the commissioned scale (any zero and gain within their bands) can give
    an angle from `min_deg` to `max_deg`, each end widened by `signal_margin_deg`."""
    global _envelope  # noqa: PLW0603 - a one-entry cache of a pure function of a frozen model
    last = _envelope
    if last is not None and last[0] is cfg:
        return last[1]
    ends = (cfg.min_deg - cfg.signal_margin_deg, cfg.max_deg + cfg.signal_margin_deg)
    zeros = (cfg.zero_min_counts, cfg.zero_max_counts)
    gains = (cfg.gain_min_counts_per_deg, cfg.gain_max_counts_per_deg)
    values = [zero + gain * deg for zero in zeros for gain in gains for deg in ends]
    _envelope = (cfg, (min(values), max(values)))
    return _envelope[1]


def signal_fault(raw: int, cfg: TiltSection) -> Fault | None:
    """`TILT_SIGNAL_RANGE` for a raw value no tilt the ride can take reads (an open circuit
    reads 0, a short full scale), at rest as in motion; None for one it can."""
    lo, hi = raw_envelope(cfg)
    if lo <= raw <= hi:
        return None
    return Fault(
        code=FaultCode.TILT_SIGNAL_RANGE,
        message=f"tilt sensor reads {raw} counts, outside the {lo:.0f}..{hi:.0f} that any tilt"
        f" from {cfg.min_deg - cfg.signal_margin_deg:g}° to"
        f" {cfg.max_deg + cfg.signal_margin_deg:g}° gives on the commissioned scale: a broken"
        " wire (an open circuit reads 0), a short, or a sensor off its shaft",
        axis="tilt",
    )
