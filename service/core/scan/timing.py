"""Cycle statistics, as a PLC task monitor keeps them: execution time, jitter, overruns."""

from __future__ import annotations

from array import array
from bisect import bisect_left, bisect_right

from ride_machine.schema.diag import CycleDiag, TimingStats

JITTER, EXECUTION = 0, 1
"""Where each series sits in a cycle's pair of ring slots."""
SORT_CHUNK = 4096
"""Samples sorted in one call when a report picks its percentiles. A sort holds the GIL, which
the scan thread may be waiting for: a 100,000-cycle window sorted at once held it for ~17 ms
once a second (the `diag` publisher). A larger window is sorted in chunks of this size (each
well under a millisecond), and the percentiles are picked from the sorted chunks."""


class _Window:
    """The samples since one reset: both series interleaved in one ring of recent cycles (for
    the percentiles) and their running min/max/total. A reset swaps in a new one, so the scan
    thread never writes into a half-reset window."""

    __slots__ = (
        "count",
        "e_hi",
        "e_lo",
        "e_total",
        "filled",
        "j_hi",
        "j_lo",
        "j_total",
        "missed",
        "overruns",
        "pos",
        "ring",
        "since",
        "size",
        "stall_max",
        "stalls",
        "trips",
    )

    def __init__(self, window: int, since: float) -> None:
        self.size = 2 * window
        self.ring = array("d", bytes(8 * self.size))
        self.pos = 0
        """The next cycle's first slot (its jitter; the execution time follows)."""
        self.filled = 0
        """Cycles in the ring (up to the window)."""
        self.count = 0
        self.j_total = self.e_total = 0.0
        self.j_lo = self.e_lo = float("inf")
        self.j_hi = self.e_hi = 0.0
        self.overruns = 0
        self.missed = 0
        self.stalls = 0
        self.trips = 0
        self.stall_max = 0.0
        self.since = since

    def stats(self, series: int) -> TimingStats:
        """One series' figures; read from any thread while the scan thread records."""
        if self.count == 0:
            return TimingStats()
        ring, filled = self.ring, self.filled
        p50, p99 = percentiles(ring[series : 2 * filled : 2], (0.50, 0.99))
        lo, hi, total = (
            (self.j_lo, self.j_hi, self.j_total)
            if series == JITTER
            else (self.e_lo, self.e_hi, self.e_total)
        )
        return TimingStats(
            last=ring[(self.pos - 2 + series) % self.size],
            mean=total / self.count,
            min=lo,
            max=hi,
            p50=p50,
            p99=p99,
        )


def percentiles(
    values: array[float], qs: tuple[float, ...], chunk: int = SORT_CHUNK
) -> list[float]:
    """The `qs` percentiles of `values` (non-empty): for each q the value at index
    round(q × (n − 1)) of the sorted values, as one full sort gives it, however many chunks."""
    n = len(values)
    chunks = [sorted(values[i : i + chunk]) for i in range(0, n, chunk)]
    return [_kth(chunks, min(n - 1, max(0, round(q * (n - 1))))) for q in qs]


def _kth(chunks: list[list[float]], k: int) -> float:
    """The k-th smallest value (from 0) of the union of sorted lists.

    The chunk with the widest part still open offers its middle value v; counting, by
    bisection, the values below and up to v in every chunk says whether v is the k-th, or
    which side of v it lies on, and every chunk's open part shrinks to that side (v itself
    leaves it). About chunks × log2(chunk) rounds of `2 × chunks` bisections."""
    if len(chunks) == 1:
        return chunks[0][k]
    lo = [0] * len(chunks)
    hi = [len(c) for c in chunks]
    while True:
        j = max(range(len(chunks)), key=lambda i: hi[i] - lo[i])
        v = chunks[j][(lo[j] + hi[j]) // 2]
        below = [bisect_left(c, v) for c in chunks]
        upto = [bisect_right(c, v) for c in chunks]
        if sum(below) <= k < sum(upto):
            return v
        if k < sum(below):  # the k-th is below v
            hi = [min(h, b) for h, b in zip(hi, below, strict=True)]
        else:  # above v
            lo = [max(low, u) for low, u in zip(lo, upto, strict=True)]


class CycleStats:
    """Written by the scan thread only; `diag()` may be called from any thread (GIL-safe reads)."""

    def __init__(
        self, period_s: float, window: int = 1000, now: float = 0.0, limit_s: float | None = None
    ) -> None:
        self.period_s = period_s
        self.limit_s = limit_s
        """The watchdog limit, for the report."""
        self.window = window
        self.cycles = 0
        self.commands = 0
        self._w = _Window(window, now)

    def reset(self, now: float) -> None:
        """Clear min/max/mean, the overrun counter and missed cycles (the resettable counters)."""
        self._w = _Window(self.window, now)

    @property
    def overruns(self) -> int:
        return self._w.overruns

    @property
    def missed_cycles(self) -> int:
        return self._w.missed

    def record(self, jitter_s: float, exec_s: float, missed: int) -> None:
        # Every cycle: one object and one ring, plain compares, no calls (after a 10 ms sleep
        # each object and call touched costs microseconds of cold caches: BENCHMARKS.md §5).
        self.cycles += 1
        w = self._w
        pos = w.pos
        ring = w.ring
        ring[pos] = jitter_s
        ring[pos + 1] = exec_s
        pos += 2
        w.pos = 0 if pos == w.size else pos
        if w.filled < self.window:
            w.filled += 1
        w.count += 1
        w.j_total += jitter_s
        w.e_total += exec_s
        if jitter_s < w.j_lo:  # noqa: PLR1730 - a compare, not a builtin call, every cycle
            w.j_lo = jitter_s
        if jitter_s > w.j_hi:  # noqa: PLR1730 - likewise
            w.j_hi = jitter_s
        if exec_s < w.e_lo:  # noqa: PLR1730 - likewise
            w.e_lo = exec_s
        if exec_s > w.e_hi:  # noqa: PLR1730 - likewise
            w.e_hi = exec_s
        if missed:
            w.overruns += 1
            w.missed += missed

    def stall(self, stalled_s: float, tripped: bool) -> None:
        """A scan that completed no cycle for the watchdog limit; `tripped`: an output was
        energised and the watchdog forced the outputs safe."""
        w = self._w
        w.stalls += 1
        w.trips += tripped
        w.stall_max = max(w.stall_max, stalled_s)

    def diag(self, now: float) -> CycleDiag:
        w = self._w
        return CycleDiag(
            period_s=self.period_s,
            cycles=self.cycles,
            execution=w.stats(EXECUTION),
            jitter=w.stats(JITTER),
            overruns=w.overruns,
            missed_cycles=w.missed,
            commands=self.commands,
            window=w.filled,
            since=w.since,
            time=now,
            stalls=w.stalls,
            longest_stall_s=w.stall_max,
            watchdog_trips=w.trips,
            watchdog_limit_s=self.limit_s,
        )
