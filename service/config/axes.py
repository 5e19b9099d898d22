"""The axes' sections of the machine config (`[rotate]`, `[tilt]`): speeds, timeouts, the
witnesses' tolerances and the tilt sensor's commissioned scale."""

from __future__ import annotations

from pydantic import Field

from .section import _Section


class RotateSection(_Section):
    """The rotate axis: a relay + direction, and a home switch once per revolution."""

    nominal_speed_dps: float = Field(default=90.0, gt=0, le=3600)
    home_arc_deg: float = Field(default=10.0, gt=0, lt=180)
    revolution_timeout_s: float = Field(default=8.0, gt=0, le=600)
    backoff_timeout_s: float = Field(default=2.0, gt=0, le=60)
    speed_tolerance: float = Field(default=0.5, gt=0, lt=1)
    settle_window_deg: float = Field(default=2.0, gt=0, le=30)
    latch_tolerance_deg: float = Field(default=0.5, gt=0, le=90)
    """The home edge is latched from the scans either side of it: half the travel between them
    (nominal or calibrated speed × gap / 2) may be at most this, or it is approached again."""
    latch_attempts: int = Field(default=5, ge=1, le=20)
    """Approaches (or extra revolutions of a calibration) before `HOME_EDGE_UNCERTAIN`."""
    runup_s: float = Field(default=0.05, ge=0, le=10)
    """Backing off, the axis goes on this long past where the switch opened (the run-up)."""
    repeat_tolerance_deg: float = Field(default=2.0, gt=0, le=90)
    """Calibration times the revolution twice (closing and opening edges): they may differ by
    at most this many degrees of travel, or `CALIBRATION_NOT_REPEATABLE` (two timings from
    edges each latched to ±`latch_tolerance_deg` may differ by 4 × that)."""
    revolution_tolerance: float = Field(default=0.1, gt=0, lt=1)
    """In a session each revolution takes the calibrated time ± this fraction, or the motion
    stops (`ROTATE_HOME_TIMEOUT` overdue, `ROTATE_SPEED_IMPLAUSIBLE` early)."""


class TiltSection(_Section):
    """The tilt axis: a relay + direction, an analog position, a home switch at 0°."""

    nominal_speed_dps: float = Field(default=15.0, gt=0, le=360)
    min_deg: float = Field(default=0.0, ge=-90, le=90)
    max_deg: float = Field(default=60.0, ge=-90, le=120)
    tolerance_deg: float = Field(default=1.0, gt=0, le=10)
    home_timeout_s: float = Field(default=10.0, gt=0, le=600)
    move_timeout_margin_s: float = Field(default=2.0, ge=0, le=600)
    follow_window_s: float = Field(default=0.5, gt=0, le=60)
    follow_min_counts: int = Field(default=4, ge=1, le=10_000)
    noise_jump_counts: int = Field(default=60, ge=1, le=65_535)
    noise_max_jumps: int = Field(default=3, ge=1, le=1000)
    calibration_stroke_s: float = Field(default=2.0, gt=0, le=60)
    calibration_samples: int = Field(default=10, ge=1, le=1000)
    gain_min_counts_per_deg: float = Field(default=38.0, gt=0)
    gain_max_counts_per_deg: float = Field(default=42.0, gt=0)
    """The tilt sensor's commissioned scale: its gain (counts per degree, rising going up) from
    the datasheet and the gearing, ± what they allow (here the simulator's 40 ± 5 %), and its
    raw value at the home switch (`zero_min_counts`..`zero_max_counts`). A calibration measured,
    entered or loaded outside either is refused: the stroke's gain comes from the drive's
    nominal speed, so a drive off its speed calibrates off by as much and every speed witness
    agrees with it; this band is what bounds that error (docs/homing.md)."""
    signal_margin_deg: float = Field(default=20.0, gt=0, le=180)
    """The tilt's raw value must always read where the commissioned scale can put an angle
    between `min_deg` and `max_deg` widened by this, or `TILT_SIGNAL_RANGE`: an open circuit
    (0) or a short (full scale) is found in the cycle it reads, at rest too."""
    zero_min_counts: float = Field(default=1160.0, ge=-1_000_000, le=1_000_000)
    zero_max_counts: float = Field(default=1240.0, ge=-1_000_000, le=1_000_000)
    """The raw value at the home switch, commissioned (here the simulator's 1200 ± 1°): a tilt
    zero outside is a switch that moved or a sensor that slipped on its shaft."""
    latch_tolerance_deg: float = Field(default=0.15, gt=0, le=10)
    """Half the travel between the scans either side of the home edge (nominal speed × gap
    / 2) may be at most this, or the edge is approached again."""
    latch_attempts: int = Field(default=5, ge=1, le=20)
    """Approaches per latch before `HOME_EDGE_UNCERTAIN`."""
    runup_s: float = Field(default=0.3, ge=0, le=10)
    """Backing off, the tilt goes on up this long past where the switch opened: the run-up of
    the next approach (at least `speed_window_s`, so the approach checks the speed)."""
    backoff_timeout_s: float = Field(default=3.0, gt=0, le=600)
    """The switch must open within this of backing off, or `TILT_HOME_STUCK`."""
    repeat_tolerance_deg: float = Field(default=0.3, gt=0, le=10)
    """Calibration latches the zero twice: they may differ by at most this, or
    `CALIBRATION_NOT_REPEATABLE`."""
    home_tolerance_deg: float = Field(default=0.5, gt=0, le=10)
    """Home latches the edge again: by the calibration it must lie within ± this of 0°, or
    `HOME_OFF_ZERO`."""
    speed_window_s: float = Field(default=0.2, gt=0, le=60)
    """While driven, the calibrated speed is measured over each window of this length …"""
    speed_tolerance: float = Field(default=0.3, gt=0, lt=1)
    """… and must be the nominal speed ± this fraction, or `TILT_SPEED_IMPLAUSIBLE`."""
    gain_tolerance_deg: float = Field(default=0.3, gt=0, le=10)
    """The drive's speed witness: over each stroke, the analog's counts per second against the
    calibrated gain at the nominal speed may disagree by at most this much position error at
    the range's far end (max |min_deg|, |max_deg|), or `TILT_GAIN_MISMATCH`. With
    `home_tolerance_deg` it bounds how far a trusted calibration may overshoot a target."""
    verify_tolerance_deg: float = Field(default=0.3, gt=0, le=10)
    """A calibration entered by hand is verified by the next Home (two zeros and a stroke):
    the position error the witnesses then find anywhere in min_deg..max_deg must be at most
    this, or `HOME_OFF_ZERO` / `TILT_GAIN_MISMATCH`."""
