"""A running process probed from outside: what it applies to every thread (a call made among
running threads), its threads' CPUs and time slices (/proc), and a storm of signals at it.
Starting and stopping the processes is tests/procs.py's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.procs import REPO

STORM_S = 0.3
STORM_GAP_S = 20e-6
"""A signal every 20 µs: standard signals do not queue, so the gap is what lets one land
while the handler of the one before still runs."""


def signal_storm(pid: int, sig: int = signal.SIGTERM) -> int:
    """`sig` at `pid` for `STORM_S`, or until it is gone; how many were sent."""
    sent = 0
    end = time.monotonic() + STORM_S
    while time.monotonic() < end:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            break
        sent += 1
        gap = time.perf_counter() + STORM_GAP_S
        while time.perf_counter() < gap:
            pass  # sleeping would space them by the timer slack, 50 µs or more
    return sent


_AROUND_THREADS = """
import os, sys, threading
{setup}
started, go = threading.Barrier(3), threading.Event()
def body():
    started.wait(10)
    go.wait(10)
before = [threading.Thread(target=body) for _ in range(2)]
for t in before:
    t.start()
started.wait(10)  # two threads run before the call
print({call}, flush=True)
after = threading.Thread(target=go.wait, args=(10,))
after.start()  # and one after it
print({report}, flush=True)
go.set()
"""


def call_among_threads(setup: str, call: str, report: str, arg: str) -> tuple[str, str]:
    """In a child process (`setup`: its imports) with two threads running, `call` (an
    expression of `sys.argv[1]`, `arg`), then a third thread started, then `report` (an
    expression of `os.getpid()`): what each printed. For what a process applies to every
    thread: to those before and to those after."""
    code = _AROUND_THREADS.format(setup=setup, call=call, report=report)
    proc = subprocess.run(
        [sys.executable, "-c", code, arg],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    applied, threads = proc.stdout.splitlines()
    return applied, threads


def thread_cpus(pid: int) -> dict[int, tuple[int, ...]]:
    """The CPUs each thread of a process may run on, by thread id (threads that end while
    being read are left out)."""
    cpus: dict[int, tuple[int, ...]] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            cpus[int(tid)] = tuple(sorted(os.sched_getaffinity(int(tid))))
        except ProcessLookupError:
            continue
    return cpus


def thread_slices(pid: int) -> dict[int, int]:
    """Each thread's time slice in ns as the kernel shows it (`se.slice` in
    /proc/<pid>/task/<tid>/sched), by thread id (threads that end while being read are left
    out)."""
    slices: dict[int, int] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            text = Path(f"/proc/{pid}/task/{tid}/sched").read_text()
        except (FileNotFoundError, ProcessLookupError):
            continue
        for line in text.splitlines():
            name, _, value = line.partition(":")
            if name.strip() == "se.slice":
                slices[int(tid)] = int(value)
    return slices
