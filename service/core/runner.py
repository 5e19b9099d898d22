"""The real-time runner: absolute deadlines, early wake for commands, timing statistics."""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import os
import platform
import signal
import sys
import threading
import time
from collections.abc import Callable

from schema.status import Fault, FaultCode
from service.core.beat import BeatWriter
from service.core.loop import ScanLoop
from service.core.timing import CycleStats
from service.core.watchdog import ARM_AFTER_CYCLES
from service.threads import libc, prctl

log = logging.getLogger(__name__)

MAX_CONSECUTIVE_ERRORS = 50
"""A loop that fails this many cycles in a row stops the daemon (a supervisor restarts it)."""

TIMER_SLACK_NS = 1_000
"""The scan thread's timer slack. Linux lets a timed wait end up to 50 µs late by default,
which was half of the median wake-up jitter measured at 1 ms (bench/loop_timing.py)."""
SCHED_SLICE_NS = 100_000
"""The daemon's time slice under the normal policy: Linux's EEVDF scheduler (6.12 and later)
gives a thread that asks for a short slice an early deadline, so its wake-up preempts a busy
neighbour at once instead of waiting out the neighbour's slice (the kernel's default slice,
1.4 ms on two CPUs, is longer than a 1 ms period). Every thread, not the scan thread alone:
the scan waits for the GIL, and a Zenoh callback that holds it must not wait out a neighbour's
slice either. No privilege and no priority: each thread's share of the CPU is unchanged
(BENCHMARKS.md section 2). 100 µs is the shortest the kernel grants."""
_SCHED_ATTR_CALLS = {
    "x86_64": (314, 315),
    "aarch64": (274, 275),
    "riscv64": (274, 275),
    "armv7l": (380, 381),
    "armv6l": (380, 381),
    "armv8l": (380, 381),  # a 32-bit userland on a 64-bit ARM kernel
    "i686": (351, 352),
}
"""`sched_setattr(2)` and `sched_getattr(2)` by machine (no C library wraps them)."""
CLOCK_STEP_S = 0.01
"""A change of the host's wall clock against the steady clock larger than this is one the
machine's wall times follow (`RealtimeRunner`'s `wall`); NTP's slewing moves both clocks alike."""
CLOCK_SET_S = 0.1
"""A change larger than this, seen at once, is the clock being set (NTP steps from 128 ms): it is
logged and recorded (`clock_set`). Smaller ones are a drift, followed without a word: a host
whose wall clock runs apart from its steady clock (a virtual machine's, 5 ms a second on the
project's test host) would otherwise record a `clock_set` event every two seconds."""
WALL_READ_MAX_S = 0.001
"""Both clocks read within this, or the sample is left for the next cycle (the thread was
preempted between the reads, which would look like a step)."""
PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30
PR_SET_PDEATHSIG = 1
SUPERVISOR_PID_ENV = "MACHINE_SUPERVISOR_PID"
"""Set by `machine supervise` for its child: the daemon stops when the supervisor dies."""


class LoopFailed(Exception):
    """The scan loop kept failing; outputs were made safe before this was raised."""


class RealtimeRunner:
    """Runs `ScanLoop.step` on absolute deadlines and records how well it kept them.

    Between deadlines it sleeps on the inbox's event, so a command is answered as soon as it
    arrives instead of at the next cycle; the last `spin_s` before a deadline is busy-waited.
    On an overrun it counts the missed cycles and skips to the next future deadline.
    """

    def __init__(
        self,
        loop: ScanLoop,
        period_s: float,
        stats: CycleStats,
        *,
        spin_s: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
        stall_limit_s: float | None = None,
        beat: BeatWriter | None = None,
        wall: Callable[[], float] | None = None,
    ) -> None:
        """`stall_limit_s`: a cycle that starts this long after the previous one ended is a
        stall, judged by `on_stall` before the cycle runs. `beat`: the record a supervisor
        watches from its own process, stamped after every cycle. `wall`: the host's wall
        clock, compared with `clock` before every cycle: when it was set (NTP's first sync on a
        Revolution Pi, which has no battery clock; a resumed virtual machine) the loop's wall
        times follow it (`ScanLoop.set_wall_offset`), or every motion command's timecode would
        be judged against the clock the daemon started with."""
        self.loop = loop
        self.period = period_s
        self.stats = stats
        self.spin_s = spin_s
        self.clock = clock
        self.stop_event = threading.Event()
        self._stopping = False
        """`stop_event` as a plain bool, read every cycle (an `Event` read is a Python call)."""
        self.heartbeat = 0
        """Incremented after every completed cycle; the watchdog reads it."""
        self.beat_at = clock()
        """The clock time the latest cycle ended (set just before `heartbeat` moves)."""
        self.errors = 0
        self.finished = False
        """Set once the cycling has ended (stopped or failed), just before the outputs go safe."""
        self.stall_limit = stall_limit_s
        self.on_stall: Callable[[float, float], bool] | None = None
        """`(now, stalled_s) -> tripped`, on the scan thread (the watchdog's `after_stall`)."""
        self.beat = beat
        self.wall = wall

    def stop(self) -> None:
        self._stopping = True
        self.stop_event.set()
        self.loop.inbox.wake.set()

    def run(self) -> None:
        """Cycle until `stop()`; outputs are forced safe on every way out."""
        try:
            self._run()
        finally:
            self.finished = True  # no cycle runs any more: nothing for the watchdog to watch
            self.loop.go_safe()
            if self.beat is not None:
                self.beat.finish()

    def _run(self) -> None:
        clock, period = self.clock, self.period
        loop, stats = self.loop, self.stats
        lock = loop.lock
        limit = self.stall_limit if self.stall_limit is not None else float("inf")
        shared = self.beat.rec if self.beat is not None else None
        guard = loop.guard
        wall = self.wall
        deadline = clock()  # first scan at once: commands need a real input image
        consecutive = 0
        while self._sleep_until(deadline):
            with lock:
                start = clock()
                if wall is not None:
                    self._follow_wall(wall, start)
                if start - self.beat_at > limit:  # stopped between cycles
                    self._stalled(start, start - self.beat_at)
                try:
                    loop.step(start)
                    consecutive = 0
                except Exception as exc:  # noqa: BLE001 - any failure must end in safe outputs
                    consecutive += 1
                    self._on_error(exc, start, consecutive)
                end = clock()
                if end - start > limit:  # stopped inside this cycle: safe before the next
                    self._stalled(end, end - start)
            jitter = start - deadline
            deadline += period
            missed = 0
            if end > deadline:
                missed = int((end - deadline) // period) + 1
                deadline += missed * period
            stats.record(jitter, end - start, missed)
            stats.commands = loop.commands_handled
            self.beat_at = end
            self.heartbeat += 1
            if shared is not None:
                shared.cycles = self.heartbeat  # the supervised world waits on scans (sim/world)
                if guard is not None:  # what the relays did, for a stall found with them off
                    shared.energised = guard.energised
                shared.beat_ns = int(end * 1e9)  # one store: what the supervisor watches

    def _follow_wall(self, wall: Callable[[], float], now: float) -> None:
        clock = self.clock
        before = clock()
        at = wall()
        after = clock()
        if after - before > WALL_READ_MAX_S:
            return
        offset = at - (before + after) / 2
        step = abs(offset - self.loop.wall_offset)
        if step > CLOCK_STEP_S:
            self.loop.set_wall_offset(offset, now, record=step > CLOCK_SET_S)

    def _sleep_until(self, deadline: float) -> bool:
        """Wait for the deadline on the inbox's event, serving commands as they come; the
        last `spin_s` busy-waited. False once stopped."""
        clock, spin, loop = self.clock, self.spin_s, self.loop
        wake = loop.inbox.wake
        while not self._stopping:
            remaining = deadline - clock()
            if remaining <= spin:
                while spin and clock() < deadline:
                    pass
                return not self._stopping
            if wake.wait(remaining - spin):
                if self._stopping:
                    return False
                with loop.lock:
                    loop.service_inbox(clock())
        return False

    def _stalled(self, now: float, stalled_s: float) -> None:
        """No cycle for longer than the limit (the process was stopped, starved or blocked):
        the watchdog judges it before this cycle runs; it is counted either way. The first
        cycles (start-up work) are not judged."""
        if self.heartbeat < ARM_AFTER_CYCLES:
            return
        tripped = self.on_stall(now, stalled_s) if self.on_stall is not None else False
        self.stats.stall(stalled_s, tripped)

    def _on_error(self, exc: Exception, now: float, consecutive: int) -> None:
        self.errors += 1
        try:
            self.loop.go_safe()
        finally:
            if consecutive == 1:
                log.error("event=loop_exception error=%r", exc, exc_info=exc)
                self.loop.control.external_fault(
                    Fault(code=FaultCode.LOOP_EXCEPTION, message=f"scan loop failed: {exc!r}"),
                    now,
                )
        if consecutive >= MAX_CONSECUTIVE_ERRORS:
            raise LoopFailed(f"scan loop failed {consecutive} cycles in a row: {exc!r}") from exc


def pin_process(cpus: list[int]) -> str | None:
    """Every thread of the process on `cpus` (threads started later inherit it from the one
    that starts them); what was applied, or None (refused: logged, and every thread left on
    the CPUs it had)."""
    before = os.sched_getaffinity(0)
    try:
        _pin_threads(set(cpus))
    except OSError as exc:
        with contextlib.suppress(OSError):
            _pin_threads(before)
        log.warning("event=affinity_failed cpus=%s error=%r", _cpu_list(cpus), exc.strerror)
        return None
    return f"cpus={_cpu_list(cpus)}"


def _pin_threads(cpus: set[int]) -> None:
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(ProcessLookupError):  # a thread that has just ended
            os.sched_setaffinity(int(tid), cpus)


def _cpu_list(cpus: list[int]) -> str:
    return "+".join(str(c) for c in sorted(set(cpus)))


def tune_thread(
    gc_freeze: bool,
    cpu: int | None,
    rt_priority: int | None,
    timer_slack_ns: int | None = TIMER_SLACK_NS,
) -> list[str]:
    """Apply the real-time measures that help hold short periods; returns what was applied."""
    applied: list[str] = []
    if timer_slack_ns is not None and set_timer_slack(timer_slack_ns):
        applied.append(f"timer_slack={timer_slack_ns}ns")
    if gc_freeze:
        # Objects from start-up never get scanned again; young collections stay short.
        gc.collect()
        gc.freeze()
        applied.append("gc_freeze")
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
            applied.append(f"cpu={cpu}")
        except OSError as exc:
            log.warning("event=affinity_failed cpu=%d error=%r", cpu, exc.strerror)
    if rt_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
            applied.append(f"SCHED_FIFO={rt_priority}")
        except (OSError, AttributeError) as exc:
            log.warning("event=sched_fifo_failed priority=%d error=%r", rt_priority, exc)
    return applied


def gc_threshold(young: int) -> str:
    """How many young objects start a garbage collection, for the process (the older
    generations' thresholds are Python's)."""
    _, middle, old = gc.get_threshold()
    gc.set_threshold(young, middle, old)
    return f"gc_threshold={young}"


def switch_interval(seconds: float) -> str:
    """How long any Python thread keeps the GIL once another one wants it, for the process.

    A Zenoh callback running commands back to back kept it for Python's default 5 ms each
    time the scan thread gave it up for a moment (a publication): a cycle needing it a few
    times ran past its period (bench.throughput: 13 overruns in 48 s at 5 ms, 2 at 0.5 ms)."""
    sys.setswitchinterval(seconds)
    return f"switch_interval={seconds:g}s"


def die_with_parent(parent_pid: int) -> bool:
    """Get SIGTERM (the safe shutdown path) when the parent process dies; False if the parent
    is already gone or the OS cannot do it."""
    ok = prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    return ok and os.getppid() == parent_pid


def timer_slack() -> int | None:
    """The calling thread's timer slack in ns (Linux); None where it cannot be read."""
    lib = libc()
    if lib is None:
        return None
    value = int(lib.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0))
    return value if value >= 0 else None


class _SchedAttr(ctypes.Structure):
    """`struct sched_attr` as the kernel's first version laid it out (48 bytes)."""

    _fields_ = [
        ("size", ctypes.c_uint32),
        ("sched_policy", ctypes.c_uint32),
        ("sched_flags", ctypes.c_uint64),
        ("sched_nice", ctypes.c_int32),
        ("sched_priority", ctypes.c_uint32),
        ("sched_runtime", ctypes.c_uint64),
        ("sched_deadline", ctypes.c_uint64),
        ("sched_period", ctypes.c_uint64),
    ]


def sched_slice(tid: int = 0) -> int | None:
    """A thread's time slice in ns as the kernel holds it (`tid` 0: the calling thread); None
    where it cannot say (not Linux, a machine not in the table, a kernel before 6.12)."""
    calls, lib = _sched_attr_calls(), libc()
    if calls is None or lib is None:
        return None
    attr = _SchedAttr()
    if lib.syscall(calls[1], tid, ctypes.byref(attr), ctypes.sizeof(attr), 0) != 0:
        return None
    return int(attr.sched_runtime) or None


def set_sched_slice(ns: int, tid: int = 0) -> bool:
    """Ask for a time slice of `ns` for one thread (`tid` 0: the calling thread) under the
    normal policy, its nice value kept; False where refused or impossible. A thread under
    another policy (SCHED_FIFO: no slice) is left alone (True). The kernel clamps the slice to
    0.1-100 ms, and one before 6.12 takes the call and ignores it: `sched_slice` tells."""
    calls, lib = _sched_attr_calls(), libc()
    if calls is None or lib is None:
        return False
    if os.sched_getscheduler(tid) != os.SCHED_OTHER:
        return True
    attr = _SchedAttr(
        size=ctypes.sizeof(_SchedAttr),
        sched_policy=os.SCHED_OTHER,
        sched_nice=os.getpriority(os.PRIO_PROCESS, tid),  # a thread's own, on Linux
        sched_runtime=ns,
    )
    return int(lib.syscall(calls[0], tid, ctypes.byref(attr), 0)) == 0


def slice_process(ns: int) -> str | None:
    """Every thread of the process on a time slice of `ns` (threads and processes started
    later inherit it from the one that starts them); what was applied, or None (logged: the
    kernel's slice stays)."""
    refused = 0
    for tid in os.listdir("/proc/self/task") if sys.platform == "linux" else []:
        try:
            refused += not set_sched_slice(ns, int(tid))
        except ProcessLookupError:  # a thread that has just ended
            continue
    held = sched_slice()
    if held != ns or refused:
        log.warning("event=slice_not_applied ns=%d held=%s refused=%d", ns, held, refused)
        return None
    return f"slice={ns}ns"


def _sched_attr_calls() -> tuple[int, int] | None:
    return _SCHED_ATTR_CALLS.get(platform.machine()) if sys.platform == "linux" else None


def set_timer_slack(ns: int) -> bool:
    """Set the calling thread's timer slack (Linux); False where that is not possible."""
    ok = prctl(PR_SET_TIMERSLACK, ns)
    if not ok and sys.platform.startswith("linux"):
        log.warning("event=timer_slack_failed ns=%d errno=%d", ns, ctypes.get_errno())
    return ok
