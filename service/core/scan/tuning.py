"""The OS tuning of the daemon's process and its scan thread: timer slack, the scheduler's time
slice, CPU affinity, SCHED_FIFO, the garbage collector and the GIL's switch interval, and the
parent-death signal of a supervised daemon. Each measure is Linux's own (prctl, sched_setattr,
sched_setaffinity); each reports what it applied for the start line (`tuning=…`), and one the
host refuses is a warning, never a stop (service/config/host.py says so before the start)."""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import os
import platform
import signal
import sys

from ride_machine.service.threads import libc, prctl

log = logging.getLogger(__name__)

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
PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30
PR_SET_PDEATHSIG = 1
SUPERVISOR_PID_ENV = "MACHINE_SUPERVISOR_PID"
"""Set by `machine supervise` for its child: the daemon stops when the supervisor dies."""


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
