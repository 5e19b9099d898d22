"""Structured logs: one `key=value` line per event, written to stderr by a thread of their own.

A line is queued by the thread that logs it (the scan thread, a command's Zenoh callback) and
written by the log writer: a reader of stderr that stalls (a frozen log collector, a full pipe)
never stalls the scan loop or a command's reply. Lines beyond `LOG_QUEUE_LINES` are dropped,
and the next line queued is preceded by one that says how many went missing. Every line queued
before the process exits normally is written (`atexit`); a process killed outright loses at
most the last `COALESCE_S` of lines.

The writer writes what is queued in one `write` per batch, not one per line. A line logged
once per command (`info`) can skip `logging`'s record: where the daemon's own handler is the
only one that would see it, the line is made as text and queued as it is.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import sys
import threading
import time
from collections import deque
from typing import Any

from .threads import NamedThread

_second: tuple[int, str] = (-1, "")
"""The last second formatted, and its text: one tuple, so a thread reads both of one second."""


def _stamp(created: float) -> str:
    """`2025-11-28T03:20:00.125Z`: one strftime per second, not per line (a line per command)."""
    global _second  # noqa: PLW0603 - a cache shared by every line
    second = int(created)
    cached, text = _second
    if second != cached:
        text = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(second))
        _second = (second, text)
    return f"{text}.{int((created - second) * 1000):03d}Z"


def _line(created: float, level: str, logger: str, message: str) -> str:
    """One log line: `ts=... level=... logger=... <message>`."""
    name = logger.removeprefix("ride_machine.")  # as the folders name it: service.bus
    return f"ts={_stamp(created)} level={level} logger={name} {message}"


class KeyValueFormatter(logging.Formatter):
    """`ts=... level=... logger=... event=...`: greppable and machine-parsable."""

    def format(self, record: logging.LogRecord) -> str:
        line = _line(record.created, record.levelname.lower(), record.name, record.getMessage())
        if record.exc_info:
            line += " traceback=" + repr(self.formatException(record.exc_info))
        return line


LOG_QUEUE_LINES = 10_000
"""Lines waiting for the writer; beyond this they are dropped, and a line where they went missing
says how many."""
COALESCE_S = 0.01
"""How long the writer gathers lines after the first one: one wake-up per batch, not per line
(a wake per line took the GIL from the thread replying to the next command)."""
WRITE_MAX = 256
"""Lines written in one `write` at most (a stalled reader holds no more than these)."""

Item = logging.LogRecord | str | None
"""A queued line: a record, a line already made (`info`), or None (the writer's stop)."""


class LineQueue:
    """The queue between the loggers and `LineWriter`: bounded, never blocks the logging
    thread, and wakes the writer once per batch."""

    def __init__(self, capacity: int = LOG_QUEUE_LINES) -> None:
        self.capacity = capacity
        self.dropped = 0
        self._items: deque[Item] = deque()
        self._wake = threading.Event()

    def put_nowait(self, record: Item) -> None:
        """Queue a record or a line, or drop and count it when the queue is full; the first
        one queued after a loss is preceded by a line that says how many went missing there.
        `None` (the writer's stop sentinel) is queued even when full."""
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

    def take(self, limit: int) -> list[Item]:
        """The next batch, for the writer: waits for its first line, then a moment for the
        rest, so a burst of lines costs one wake-up (and one write)."""
        items = self._items
        while not items:
            self._wake.clear()
            if items:  # queued between the check and the clear
                break
            self._wake.wait()
            time.sleep(COALESCE_S)
        return [items.popleft() for _ in range(min(limit, len(items)))]

    def _dropped_line(self) -> logging.LogRecord:
        dropped, self.dropped = self.dropped, 0
        return logging.LogRecord(
            "ride_machine.service.logfmt",
            logging.WARNING,
            __file__,
            0,
            "event=log_lines_dropped count=%d reason=%r",
            (dropped, "stderr was not read fast enough"),
            None,
        )


class LineHandler(logging.Handler):
    """Queues each record for the writer thread, its message made. A plain `Handler`: what
    `logging.handlers.QueueHandler` adds to it is `emit` below and its own `prepare` (replaced
    here), and its module brings `pickle`, `socket` and `queue` into a process that needs none
    of them (~1 MiB of the event history's process, bench.rss_soak)."""

    def __init__(self, queue: LineQueue) -> None:
        super().__init__()
        self.queue = queue

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.queue.put_nowait(self.prepare(record))
        except Exception:  # noqa: BLE001 - logging's rule: a broken line is reported, not raised
            self.handleError(record)

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


class LineWriter:
    """The thread that writes the queued lines to `stream` (None: whatever `sys.stderr` is when
    a batch is written, as logging's own last-resort handler does), one write per batch."""

    def __init__(self, lines: LineQueue, stream: Any = None) -> None:
        self.lines = lines
        self.stream = stream
        self.formatter = KeyValueFormatter()
        self._thread = NamedThread(target=self._run, name="log-writer", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """Write every line queued so far, then end the thread (waiting at most `timeout`)."""
        self.lines.put_nowait(None)
        self._thread.join(timeout)

    def _run(self) -> None:
        fmt = self.formatter.format
        while True:
            batch = self.lines.take(WRITE_MAX)
            text = []
            for item in batch:
                if item is None:
                    break
                text.append(item if isinstance(item, str) else fmt(item))
            if text:
                self._write("\n".join(text) + "\n")
            if None in batch:
                return

    def _write(self, text: str) -> None:
        stream = self.stream if self.stream is not None else sys.stderr
        try:
            stream.write(text)
            stream.flush()
        except Exception:  # noqa: BLE001 - a closed or broken stderr must not end the writer
            pass


_writer: LineWriter | None = None
_handler: LineHandler | None = None


FLUSH_TIMEOUT_S = 2.0
"""How long the exit waits for the writer: a stderr nobody reads must not hang the exit."""


def flush_logs(timeout: float = FLUSH_TIMEOUT_S) -> None:
    """Write every queued line and stop the writer, waiting at most `timeout` (at exit, before
    `os._exit`, when `machine …` returns); lines logged after it are written at once."""
    global _writer, _handler
    writer, _writer, _handler = _writer, None, None
    if writer is None:
        return
    root = logging.getLogger()
    root.handlers[:] = [Stderr() if isinstance(h, LineHandler) else h for h in root.handlers]
    writer.stop(timeout)


class Stderr(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes each line at once to whatever `sys.stderr` is then (after the writer stopped, as
    logging's own last-resort handler does), formatted as `key=value`."""

    def __init__(self) -> None:
        super().__init__()
        self.setFormatter(KeyValueFormatter())

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, _value: Any) -> None:
        """`StreamHandler.__init__` sets it; the line goes to the current stderr anyway."""


def setup_logging(level: str = "info", stream: Any = None) -> None:
    """Log lines as `key=value` text to stderr (or `stream`: anything with `write` and
    `flush`), through the writer thread."""
    global _writer, _handler  # noqa: PLW0603 - one writer per process
    # The format names neither thread, process nor source line: don't look them up for every
    # record (the logging HOWTO's "Optimization"; a quarter of a command's log line).
    logging.logThreads = False
    logging.logProcesses = False
    logging.logMultiprocessing = False
    logging._srcfile = None
    flush_logs()
    lines = LineQueue()
    _writer = LineWriter(lines, stream)
    _writer.start()
    _handler = LineHandler(lines)
    root = logging.getLogger()
    root.handlers[:] = [_handler]
    root.setLevel(level.upper())


def put_text(text: str) -> None:
    """Lines already made elsewhere (`ts=… level=…`, one per line: the event history's own
    process, service/adapters/history.py), written with the daemon's in one queued item."""
    handler = _handler
    if handler is not None:
        handler.queue.put_nowait(text.rstrip("\n"))
        return
    with contextlib.suppress(Exception):  # a closed or broken stderr, as the writer's
        sys.stderr.write(text)
        sys.stderr.flush()


def info(logger: logging.Logger, message: str) -> None:
    """`logger.info(message)` (the message as it is, no `%` arguments), for a line logged once
    per command: where the daemon's handler is the only one the line would reach, it is made
    as text and queued without a `LogRecord` (a third of the writer's work per command); any
    other handler, filter or level (a test's capture, a library's setup) gets the record."""
    handler = _handler
    if handler is not None and logger.isEnabledFor(logging.INFO) and _only(logger, handler):
        handler.queue.put_nowait(_line(time.time(), "info", logger.name, message))
        return
    logger.info("%s", message)


def _only(logger: logging.Logger, handler: LineHandler) -> bool:
    """`handler` is the one handler a record of `logger` reaches, and no filter looks at it
    (logging applies the filters of the logger itself and of each handler, not its parents')."""
    if logger.filters or logger.disabled or handler.filters or handler.level > logging.INFO:
        return False
    seen = False
    node: logging.Logger | None = logger
    while node is not None:
        for each in node.handlers:
            if each is not handler or seen:
                return False
            seen = True
        if not node.propagate:
            break
        node = node.parent
    return seen


atexit.register(flush_logs)
