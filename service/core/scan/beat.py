"""The scan loop's heartbeat in shared memory, for a watchdog in another process.

A frozen daemon cannot protect itself: every thread of a stopped process stops, and a thread
that holds the GIL stops every other Python thread of it. So the scan thread stamps a small
record in memory shared with the supervisor (a `memfd`, inherited by the child) after every
cycle: one aligned 8-byte store of the clock, no system call, no Zenoh, no helper thread. The
supervisor's output guard (`service.supervision.outputguard`) reads it from its own process and
forces the ride's outputs safe when the stamp stops moving for the watchdog limit.

The clock is `CLOCK_MONOTONIC` in nanoseconds, which every process on the host shares. The
supervisor may also *latch* the record: the daemon's `GuardedHal` then writes nothing but the
safe state until the scan thread has put the machine into `FAULT_HW` (`WATCHDOG`), so a loop that
wakes up from a stall never re-energises a relay with decisions made before it.
"""

from __future__ import annotations

import ctypes
import mmap
import os
from dataclasses import dataclass

BEAT_FD_ENV = "MACHINE_BEAT_FD"
"""The file descriptor of the shared record, set by `machine supervise` for its child."""


class _Record(ctypes.Structure):
    """The shared layout: every field 8-byte aligned, each written with one store."""

    _fields_ = [
        # When the latest cycle ended (CLOCK_MONOTONIC ns); 0 before the first cycle.
        ("beat_ns", ctypes.c_uint64),
        # The daemon's watchdog limit: the supervisor judges the stamp by it.
        ("limit_ns", ctypes.c_uint64),
        ("cycles", ctypes.c_uint64),
        ("pid", ctypes.c_uint64),
        # Nonzero once the loop has left its cycle for good (a stop): beats end on purpose.
        ("finished", ctypes.c_uint64),
        # Set by the supervisor when it forced the outputs safe over a stall; the daemon
        # clears it once it has taken the fault.
        ("latched", ctypes.c_uint64),
        # Stalls the supervisor acted on, over the record's life (across daemon restarts).
        ("trips", ctypes.c_uint64),
        # Nonzero when the latest cycle's write left a relay of the ride on: what a stall
        # found with the relays off now was doing before (the supervisor's claim is honest).
        ("energised", ctypes.c_uint64),
    ]


RECORD_BYTES = ctypes.sizeof(_Record)
CYCLES_OFFSET: int = _Record.cycles.offset
"""Where the scan count lies in the record: what a simulated plant reads to wait for a scan
(`hal.backends.World.follow_beat`), knowing nothing else of the layout."""


def create_beat_fd() -> int:
    """A fresh record in anonymous shared memory (no file, nothing written to storage), as
    an inheritable descriptor for the child."""
    fd = os.memfd_create("machine-beat", 0)  # no MFD_CLOEXEC: the child inherits it
    os.ftruncate(fd, mmap.PAGESIZE)
    return fd


class BeatRecord:
    """The record mapped into this process (either side)."""

    def __init__(self, fd: int) -> None:
        self._map = mmap.mmap(fd, mmap.PAGESIZE, mmap.MAP_SHARED)
        self.rec = _Record.from_buffer(self._map)

    def close(self) -> None:
        del self.rec
        self._map.close()


class BeatWriter(BeatRecord):
    """The daemon's side: the runner stamps it after each cycle."""

    def start(self, limit_s: float) -> None:
        rec = self.rec
        rec.finished = 0
        rec.latched = 0
        rec.beat_ns = 0
        rec.cycles = 0
        rec.limit_ns = round(limit_s * 1e9)
        rec.pid = os.getpid()

    def finish(self) -> None:
        self.rec.finished = 1

    @property
    def latched(self) -> bool:
        return bool(self.rec.latched)

    def unlatch(self) -> None:
        self.rec.latched = 0


@dataclass(frozen=True)
class Beat:
    """One look at the record."""

    beat_ns: int
    limit_ns: int
    cycles: int
    pid: int
    finished: bool
    latched: bool
    energised: bool = False
    """The latest completed cycle left a relay of the ride on."""


class BeatReader(BeatRecord):
    """The supervisor's side."""

    def read(self) -> Beat:
        rec = self.rec
        return Beat(
            beat_ns=int(rec.beat_ns),
            limit_ns=int(rec.limit_ns),
            cycles=int(rec.cycles),
            pid=int(rec.pid),
            finished=bool(rec.finished),
            latched=bool(rec.latched),
            energised=bool(rec.energised),
        )

    def reset(self) -> None:
        """Before a new child starts: no stamp, no latch (its first beat arms the guard)."""
        rec = self.rec
        rec.beat_ns = 0
        rec.cycles = 0
        rec.finished = 0
        rec.latched = 0
        rec.pid = 0
        rec.energised = 0

    def latch(self) -> None:
        self.rec.latched = 1
        self.rec.trips += 1


def beat_from_env(env: dict[str, str] | None = None) -> BeatWriter | None:
    """The record the supervisor handed this daemon, or None (not supervised, or an old one)."""
    value = (env if env is not None else os.environ).get(BEAT_FD_ENV)
    if not value:
        return None
    return BeatWriter(int(value))
