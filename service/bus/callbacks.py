"""Callbacks Zenoh runs on its own threads, which keep their Python thread state.

A direct callback (`zenoh.handlers.Callback(fn, indirect=False)`) runs on one of Zenoh's
threads, which Python did not start. pyo3 enters Python there with `PyGILState_Ensure` and
leaves with `PyGILState_Release`; with no thread state kept between the two, each call builds
a new one and tears it down after: a `gettid`, a 16 KiB frame stack mapped and unmapped (page
faults, and a TLB shoot-down on the other CPU), the interpreter's thread list locked twice.
That was about 40 µs of every command's CPU (BENCHMARKS.md, section 1). `direct` keeps one
thread state per Zenoh thread for the life of the process, so a call only takes the GIL.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import zenoh

T = TypeVar("T")

KEPT_MAX = 64
"""Threads given a kept thread state. Zenoh's are a fixed few (`bus.zenoh_threads`); a pool
whose threads come and go would leak one (a few KiB) per thread, so past this bound a new
thread gets pyo3's default again."""

_kept: set[int] = set()


def keep_thread_state() -> None:
    """Keep the calling thread's Python thread state after the current call into Python ends.

    One `PyGILState_Ensure` never released: pyo3's own release then only drops the GIL
    instead of deleting the state (its counter stays above zero). Called with the GIL held,
    as every callback is; on a thread Python started it only raises a counter nobody reads.
    """
    ident = threading.get_ident()
    if ident in _kept or len(_kept) >= KEPT_MAX:
        return
    _kept.add(ident)
    ctypes.pythonapi.PyGILState_Ensure()


def direct(fn: Callable[[T], None]) -> zenoh.handlers.Callback[Any]:
    """`fn` run on Zenoh's own thread (no Python thread of its own, arrival order kept),
    with that thread's Python state kept between calls. `fn` must never block."""
    kept = _kept

    def run(arg: T) -> None:
        if threading.get_ident() not in kept:
            keep_thread_state()
        fn(arg)

    return zenoh.handlers.Callback(run, indirect=False)
