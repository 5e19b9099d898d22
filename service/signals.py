"""SIGTERM and SIGINT handled on a thread of their own, never inside the code they interrupt.

Python runs a signal handler on the main thread between two bytecodes, wherever that thread
is: inside a `with` of one of its own locks, the logging queue's, say. A handler that logs,
sets an `Event` or puts on a queue then waits for a lock its own thread holds, for ever: a
stream of SIGTERMs froze `machine run` that way, its scan (the main thread) stopped and the
daemon never exited (tests/service/test_signals.py). Here Python's C-level handler only writes
the signal's number to a pipe (`signal.set_wakeup_fd`), the Python-level handler does nothing,
and a thread reads the pipe and calls the real handler, where a lock is only waited for.
"""

from __future__ import annotations

import faulthandler
import io
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterable
from types import FrameType
from typing import Any

from .threads import NamedThread

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
JOIN_TIMEOUT_S = 1.0
STACKS_SIGNAL = signal.SIGUSR2
"""Every thread's stack to stderr, and the process runs on (`dump_stacks_on_signal`)."""


def dump_stacks_on_signal(sig: int = STACKS_SIGNAL) -> bool:
    """On `sig`, write every thread's Python stack to stderr (`faulthandler`): what a hung or
    slow process is doing, asked from outside (`kill -USR2 <pid>`) without stopping it. The
    dump is written by the C-level handler, so it comes even while a thread holds the GIL or a
    lock for ever, where a Python handler would never run. False where stderr is no file
    (an in-process caller's capture): nothing is registered."""
    try:
        faulthandler.register(sig, file=sys.stderr, all_threads=True, chain=False)
    except (AttributeError, ValueError, OSError, io.UnsupportedOperation):
        return False
    return True


def _nothing(signum: int, frame: FrameType | None) -> None:
    """The Python-level handler: the number is on the pipe already (set_wakeup_fd)."""


class SignalThread:
    """Calls `handler(signum)` on a thread of its own for each of `signals` the process gets,
    from `start` (on the main thread, as Python requires) until `close`."""

    def __init__(
        self, handler: Callable[[int], None], signals: Iterable[int] = STOP_SIGNALS
    ) -> None:
        self.handler = handler
        self.signals = frozenset(signals)
        self._previous: dict[int, Any] = {}
        self._previous_fd = -1
        self._pipe: tuple[int, int] | None = None
        self._thread: NamedThread | None = None

    def start(self) -> None:
        read, write = os.pipe()
        os.set_blocking(write, False)  # the C handler must never block
        self._pipe = (read, write)
        self._previous_fd = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        for sig in self.signals:
            self._previous[sig] = signal.signal(sig, _nothing)
        self._thread = NamedThread(target=self._run, args=(read,), name="signals", daemon=True)
        self._thread.start()

    def close(self, then: signal.Handlers | None = None) -> None:
        """The signals get `then` (None: the handlers from before `start`) at once, so none
        falls between two handlers; the thread ends once it has handled what came before."""
        if self._pipe is None:
            return
        for sig, previous in self._previous.items():
            signal.signal(sig, previous if then is None else then)
        signal.set_wakeup_fd(self._previous_fd)
        read, write = self._pipe
        os.close(write)  # the thread reads the end of the pipe and returns
        if self._thread is not None:
            self._thread.join(JOIN_TIMEOUT_S)
        if self._thread is None or not self._thread.is_alive():
            os.close(read)
        self._pipe = None

    def _run(self, read: int) -> None:
        while True:
            try:
                data = os.read(read, 64)
            except OSError:  # closed under a thread that outlived its join
                return
            if not data:
                return
            for signum in data:
                if signum in self.signals:
                    self._handle(signum)

    def _handle(self, signum: int) -> None:
        try:
            self.handler(signum)
        except Exception as exc:  # the next signal must still be handled
            log.error("event=signal_handler_failed signal=%d error=%r", signum, exc, exc_info=exc)
