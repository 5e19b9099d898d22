"""Cycle statistics, as a PLC task monitor keeps them: execution time, jitter, overruns."""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field

from schema.diag import CycleDiag, TimingStats


@dataclass
class _Series:
    """Running min/max/mean since reset plus a ring of recent samples for percentiles."""

    window: int
    ring: array[float] = field(init=False)
    pos: int = 0
    filled: int = 0
    count: int = 0
    total: float = 0.0
    lo: float = float("inf")
    hi: float = 0.0
    last: float = 0.0

    def __post_init__(self) -> None:
        self.ring = array("d", bytes(8 * self.window))

    def add(self, value: float) -> None:
        # Every cycle, twice: plain compares, no builtin calls (a cold cycle pays for each).
        pos = self.pos
        self.ring[pos] = value
        pos += 1
        self.pos = 0 if pos == self.window else pos
        if self.filled < self.window:
            self.filled += 1
        self.count += 1
        self.total += value
        self.last = value
        if value < self.lo:  # noqa: PLR1730 - a compare, not a builtin call, every cycle
            self.lo = value
        if value > self.hi:  # noqa: PLR1730 - likewise
            self.hi = value

    def stats(self) -> TimingStats:
        if self.count == 0:
            return TimingStats()
        recent = sorted(self.ring[: self.filled])
        return TimingStats(
            last=self.last,
            mean=self.total / self.count,
            min=self.lo,
            max=self.hi,
            p50=_pct(recent, 0.50),
            p99=_pct(recent, 0.99),
        )


def _pct(sorted_values: list[float], q: float) -> float:
    idx = min(len(sorted_values) - 1, max(0, round(q * (len(sorted_values) - 1))))
    return sorted_values[idx]


class CycleStats:
    """Written by the scan thread only; `diag()` may be called from any thread (GIL-safe reads)."""

    def __init__(self, period_s: float, window: int = 1000, now: float = 0.0) -> None:
        self.period_s = period_s
        self.window = window
        self.cycles = 0
        self.commands = 0
        self.reset(now)

    def reset(self, now: float) -> None:
        """Clear min/max/mean, the overrun counter and missed cycles (the resettable counters)."""
        self.execution = _Series(self.window)
        self.jitter = _Series(self.window)
        self.overruns = 0
        self.missed_cycles = 0
        self.since = now

    def record(self, jitter_s: float, exec_s: float, missed: int) -> None:
        self.cycles += 1
        self.jitter.add(jitter_s)
        self.execution.add(exec_s)
        if missed:
            self.overruns += 1
            self.missed_cycles += missed

    def diag(self, now: float) -> CycleDiag:
        return CycleDiag(
            period_s=self.period_s,
            cycles=self.cycles,
            execution=self.execution.stats(),
            jitter=self.jitter.stats(),
            overruns=self.overruns,
            missed_cycles=self.missed_cycles,
            commands=self.commands,
            window=min(self.window, self.execution.filled),
            since=self.since,
            time=now,
        )
