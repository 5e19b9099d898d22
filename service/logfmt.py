"""Structured logs: one `key=value` line per event, written to stderr by a thread of their own.

A line is queued by the thread that logs it (the scan thread, a command's Zenoh callback) and
written by the log writer: a reader of stderr that stalls (a frozen log collector, a full pipe)
never stalls the scan loop or a command's reply. Lines beyond `LOG_QUEUE_LINES` are dropped,
and the next line queued is preceded by one that says how many went missing. Every line queued
before the process exits normally is written (`atexit`); a process killed outright loses at
most the last `COALESCE_S` of lines.
"""

from __future__ import annotations

import atexit
import logging
import logging.handlers
import sys
import threading
import time
from collections import deque
from typing import Any


class KeyValueFormatter(logging.Formatter):
    """`ts=... level=... logger=... event=...`: greppable and machine-parsable."""

    _second = -1
    _stamp = ""

    def format(self, record: logging.LogRecord) -> str:
        second = int(record.created)
        if second != self._second:  # one strftime per second, not per line (a line per command)
            self._stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(second))
            self._second = second
        ts = self._stamp
        line = (
            f"ts={ts}.{int(record.msecs):03d}Z level={record.levelname.lower()}"
            f" logger={record.name} {record.getMessage()}"
        )
        if record.exc_info:
            line += " traceback=" + repr(self.formatException(record.exc_info))
        return line


LOG_QUEUE_LINES = 10_000
"""Lines waiting for the writer; beyond this they are dropped, and a line where they went missing
says how many."""
COALESCE_S = 0.01
"""How long the writer gathers lines after the first one: one wake-up per batch, not per line
(a wake per line took the GIL from the thread replying to the next command)."""


class LineQueue:
    """The queue between `QueueHandler` and `QueueListener`: bounded, never blocks the logging
    thread, and wakes the writer once per batch."""

    def __init__(self, capacity: int = LOG_QUEUE_LINES) -> None:
        self.capacity = capacity
        self.dropped = 0
        self._items: deque[logging.LogRecord | None] = deque()
        self._wake = threading.Event()

    def put_nowait(self, record: logging.LogRecord | None) -> None:
        """Queue a record, or drop and count it when the queue is full; the first record queued
        after a loss is preceded by a line that says how many went missing there. `None` (the
        writer's stop sentinel) is queued even when full."""
        if record is not None and len(self._items) >= self.capacity:
            self.dropped += 1
            return
        if self.dropped:
            self._items.append(self._dropped_line())
        self._items.append(record)
        if not self._wake.is_set():
            self._wake.set()

    @property
    def queued(self) -> int:
        return len(self._items)

    def get(self, block: bool = True) -> logging.LogRecord | None:
        """The next record, for the writer: waits for the first of a batch, then a moment for
        the rest, so a burst of lines costs one wake-up."""
        while True:
            try:
                return self._items.popleft()
            except IndexError:
                self._wake.clear()
                if self._items:  # queued between the pop and the clear
                    continue
                self._wake.wait()
                time.sleep(COALESCE_S)

    def _dropped_line(self) -> logging.LogRecord:
        dropped, self.dropped = self.dropped, 0
        return logging.LogRecord(
            "service.logfmt",
            logging.WARNING,
            __file__,
            0,
            "event=log_lines_dropped count=%d reason=%r",
            (dropped, "stderr was not read fast enough"),
            None,
        )

    def task_done(self) -> None:
        """`QueueListener` calls it when the queue has one (`queue.Queue`); nothing to do."""


class LineHandler(logging.handlers.QueueHandler):
    """Queues each record for the writer thread, its message made."""

    def prepare(self, record: logging.LogRecord) -> logging.LogRecord:
        """The message is made now (its arguments may change later); the line, with its
        timestamp, by the writer."""
        message = record.getMessage()
        if record.exc_info:  # a traceback's frames are not kept alive in the queue
            message += " traceback=" + repr(logging.Formatter().formatException(record.exc_info))
            record.exc_info = None
            record.exc_text = None
        record.msg = message
        record.args = None
        return record


class Stderr(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever `sys.stderr` is when a line is written (as logging's own last-resort
    handler does), formatted as `key=value`."""

    def __init__(self) -> None:
        super().__init__()
        self.setFormatter(KeyValueFormatter())

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, _value: Any) -> None:
        """`StreamHandler.__init__` sets it; the line goes to the current stderr anyway."""


_writer: logging.handlers.QueueListener | None = None


FLUSH_TIMEOUT_S = 2.0
"""How long the exit waits for the writer: a stderr nobody reads must not hang the exit."""


def flush_logs(timeout: float = FLUSH_TIMEOUT_S) -> None:
    """Write every queued line and stop the writer, waiting at most `timeout` (at exit, before
    `os._exit`, when `machine …` returns); lines logged after it are written at once."""
    global _writer
    writer, _writer = _writer, None
    if writer is None:
        return
    root = logging.getLogger()
    root.handlers[:] = [Stderr() if isinstance(h, LineHandler) else h for h in root.handlers]
    writer.enqueue_sentinel()
    thread = writer._thread
    if thread is not None:
        thread.join(timeout)


def setup_logging(level: str = "info") -> None:
    """Log lines as `key=value` text to stderr, through the writer thread."""
    global _writer  # noqa: PLW0603 - one writer per process
    # The format names neither thread, process nor source line: don't look them up for every
    # record (the logging HOWTO's "Optimization"; a quarter of a command's log line).
    logging.logThreads = False
    logging.logProcesses = False
    logging.logMultiprocessing = False
    logging._srcfile = None
    flush_logs()
    lines = LineQueue()
    _writer = logging.handlers.QueueListener(lines, Stderr())
    _writer.start()
    root = logging.getLogger()
    root.handlers[:] = [LineHandler(lines)]
    root.setLevel(level.upper())


atexit.register(flush_logs)
