"""Scan-loop diagnostics published on `machine/<id>/diag/cycle`."""

from __future__ import annotations

from .base import OpenWireModel


class TimingStats(OpenWireModel):
    """Seconds; percentiles over the recent window, min/max/mean since the last reset."""

    last: float = 0.0
    mean: float = 0.0
    min: float = 0.0
    max: float = 0.0
    p50: float = 0.0
    p99: float = 0.0


class EventsDiag(OpenWireModel):
    """The event log's writer: events written, queued, dropped (queue full), lost (write failed)."""

    written: int = 0
    queued: int = 0
    dropped: int = 0
    lost: int = 0
    failures: int = 0
    last_error: str | None = None
    file_bytes: int = 0


class CycleDiag(OpenWireModel):
    """A PLC task monitor: period, execution time, wake-up jitter, overruns, missed cycles."""

    period_s: float
    cycles: int
    execution: TimingStats
    jitter: TimingStats
    overruns: int
    missed_cycles: int
    commands: int
    window: int
    since: float
    time: float
    events: EventsDiag | None = None
    stalls: int = 0
    """Scans that completed no cycle for the watchdog limit (since the last reset), whether
    or not anything was energised."""
    longest_stall_s: float = 0.0
    watchdog_trips: int = 0
    """Stalls with an output energised: outputs forced safe, `FAULT_HW` (`WATCHDOG`)."""
    watchdog_limit_s: float | None = None
