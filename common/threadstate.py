"""Python thread states kept on threads Python did not start (Zenoh's), between callbacks.

The daemon's bus and the Rider's client both run callbacks on Zenoh's threads.

pyo3 enters Python on such a thread with `PyGILState_Ensure` and leaves with
`PyGILState_Release`; with no thread state kept between the two, each call builds a new one
and tears it down after: a `gettid`, a 16 KiB frame stack mapped and unmapped (page faults,
and a TLB shoot-down on the other CPU), the interpreter's thread list locked twice. That was
about 40 µs of every command's CPU in the daemon (BENCHMARKS.md, section 1).
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

KEPT_MAX = 64
"""Threads given a kept state. Zenoh's are a fixed few; a pool whose threads come and go
would leak one (a few KiB) per thread, so past this bound a new thread gets pyo3's default."""

_kept: set[int] = set()


def keep_thread_state() -> None:
    """Keep the calling thread's Python state after the current call into Python ends.

    One `PyGILState_Ensure` never released: pyo3's own release then only drops the GIL
    instead of deleting the state (its counter stays above zero). Called with the GIL held,
    as every callback is; on a thread Python started it only raises a counter nobody reads.
    """
    ident = threading.get_ident()
    if ident in _kept or len(_kept) >= KEPT_MAX:
        return
    _kept.add(ident)
    ctypes.pythonapi.PyGILState_Ensure()


def keeping_state(fn: Callable[[T], None]) -> Callable[[T], None]:
    """`fn` for a callback on a foreign thread: that thread's state is kept from its first call."""
    kept = _kept

    def run(arg: T) -> None:
        if threading.get_ident() not in kept:
            keep_thread_state()
        fn(arg)

    return run
