"""Zenoh's runtime layout (`ZENOH_RUNTIME`), for the daemon's bus and for the Rider alike.

Both lay out Zenoh's threads the same way (`common.zenoh_session.open_session` for a
library's first session, `use_runtime` for the daemon, for good).

Zenoh reads `ZENOH_RUNTIME` (RON) once per process, when its first session opens; later
sessions share that runtime. Zenoh's default is five runtimes with six threads (receive 2,
send, network, accept, application): a query crosses threads between its receipt and its
reply's send, each a wake-up. One thread for all of it took a command's round trip from
1.49-1.54x to 1.29-1.39x a bare echo on the daemon's side (BENCHMARKS.md, section 1), and the
Rider's side gains as much (BENCHMARKS.md, section 1, twelfth pass).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator

RUNTIME_ENV = "ZENOH_RUNTIME"
"""Zenoh's own variable for its runtime layout."""


class _FirstOpen:
    """Whether a session has opened through `first_session_on` in this process."""

    lock = threading.Lock()
    done = False


def runtime_layout(threads: int) -> str | None:
    """`ZENOH_RUNTIME` for `threads` workers: every runtime handed over to the application
    runtime, which gets them; None (Zenoh's own layout) for 0."""
    if threads == 0:
        return None
    handed = ", ".join(f"{rt}: (handover: app)" for rt in ("rx", "tx", "net", "acc"))
    return f"({handed}, app: (worker_threads: {threads}))"


def unreadable_layout(exc: BaseException) -> str | None:
    """What to say for `exc` raised by `zenoh.open` when it is Zenoh's panic over a
    `ZENOH_RUNTIME` it cannot read (pyo3's `PanicException` derives from `BaseException`
    only); None for any other exception, which is the caller's to raise as it is."""
    layout = os.environ.get(RUNTIME_ENV)
    if isinstance(exc, Exception | KeyboardInterrupt | SystemExit) or not layout:
        return None
    return f"{RUNTIME_ENV}={layout!r} cannot be read by Zenoh: {exc}"


def use_runtime(threads: int) -> str | None:
    """Lay out Zenoh's runtime for this process before its first session (the daemon's
    `bus.zenoh_threads`, for good: `first_session_on` for a library); what the start line
    shows, or None when nothing was set. A `ZENOH_RUNTIME` already in the environment is the
    operator's: it is kept, and named."""
    if os.environ.get(RUNTIME_ENV):
        return f"zenoh_runtime={RUNTIME_ENV}"
    layout = runtime_layout(threads)
    if layout is None:
        return None
    os.environ[RUNTIME_ENV] = layout
    return f"zenoh_threads={threads}"


@contextlib.contextmanager
def first_session_on(threads: int) -> Iterator[str | None]:
    """Around a library's `zenoh.open`: if it is the first through here in this process, Zenoh
    lays out its runtime for `threads` (0: Zenoh's own), and the variable is taken away again
    after, so processes this one starts later never inherit it. Yields what was applied
    (`zenoh_threads=N`, `zenoh_runtime=ZENOH_RUNTIME` for a layout already in the environment,
    which is kept, or None).

    A session this process opened before, some other way, has fixed the layout already: then
    this changes nothing. Only the first open waits for another here (the variable is
    process-wide while it is set); later ones pass straight through."""
    first = _FirstOpen
    if first.done:
        yield None
        return
    with first.lock:
        if first.done:
            yield None
            return
        operators = bool(os.environ.get(RUNTIME_ENV))
        applied = use_runtime(threads)
        try:
            yield applied
            first.done = True
        finally:
            if not operators:
                os.environ.pop(RUNTIME_ENV, None)
