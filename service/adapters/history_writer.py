"""The history process (`python -m ride_machine.service.adapters.history`): makes the events the
daemon sends down the pipe and writes them with an `EventLog` of its own, sending back what it
wrote, its
counters and its log lines (service/adapters/history.py has the daemon's side)."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.held import COMMAND_LOG, CommandFacts
from ride_machine.service.logfmt import flush_logs, info, setup_logging
from ride_machine.service.threads import name_os_thread

from .eventdb import Row, StoredRow, as_row
from .eventlog import EventLog
from .history_pipe import (
    BATCH,
    FAILED,
    FLUSH,
    FLUSHED,
    LINE,
    LOG,
    MADE,
    WROTE,
    Item,
    encode,
    messages,
    write_all,
)

SLICE_S = 0.0001
"""The history process gives way (`sched_yield`) after this much work at a time."""


class _Pipe:
    """Messages to the daemon on this process's stdout, from any of its threads."""

    def __init__(self) -> None:
        self._out = os.fdopen(1, "wb", buffering=0, closefd=False)
        self._lock = threading.Lock()

    def send(self, message: list[Any]) -> None:
        data = encode(message)
        with self._lock:
            write_all(self._out, data)


class _LogStream:
    """Where the log writer of the history process writes: back to the daemon."""

    def __init__(self, pipe: _Pipe) -> None:
        self.pipe = pipe

    def write(self, text: str) -> None:
        self.pipe.send([LOG, text])

    def flush(self) -> None:
        pass


class _Writer(EventLog):
    """The `EventLog` of the history process: after each write, its rows and counters go
    back to the daemon."""

    def __init__(self, pipe: _Pipe, path: Path, machine_id: str, settings: EventsSection) -> None:
        # Between a batch's chunks of inserts it gives way, as `_make` does between events.
        super().__init__(path, machine_id, settings, pace=os.sched_yield)
        self.pipe = pipe
        self.received = 0
        self.forwarded = 0
        """Of `dropped`, those the daemon dropped (it counts them itself)."""
        self._wrote: list[StoredRow] = []
        self.subscribe(self._wrote.extend)
        self._in_flight = 0
        """Rows of the batch being written."""

    def receive(self, rows: list[Row], dropped: int) -> None:
        with self._lock:
            self.received += len(rows)
            self.dropped += dropped
            self.forwarded += dropped
        self.put_rows(rows)

    def record_failure(self, error: str, lost: int) -> None:
        """A failure the daemon saw (an earlier process ended): written with the next batch."""
        with self._lock:
            self.writer.failure = (error, lost)

    def _take(self) -> list[Row]:
        batch = super()._take()
        self._in_flight = len(batch)
        return batch

    def _write(self, batch: list[Row]) -> None:
        super()._write(batch)
        self._in_flight = 0
        rows, self._wrote[:] = list(self._wrote), []
        # A daemon killed before this write: the rows are stored all the same (not lost), and
        # the end of its pipe ends this process.
        with contextlib.suppress(BrokenPipeError):
            self.pipe.send([WROTE, rows, self.status()])

    def status(self) -> list[Any]:
        """Its counters, and how many of the daemon's events are settled: written, dropped or
        counted lost (those neither queued nor in the batch being written)."""
        with self._lock:
            settled = self.received - len(self._items) - self._in_flight
            own_dropped = self.dropped - self.forwarded
        return [self.written, self.lost, self.failures, self.last_error, own_dropped, settled]


def _make(items: tuple[Item, ...]) -> list[Row]:
    """A batch's events as rows; a command's event and its log line made here."""
    rows: list[Row] = []
    start = time.perf_counter()
    for item in items:
        if item[0] == MADE:
            _, kind, details, wall, cycle = item
            rows.append((kind, details, wall, cycle))
        elif item[0] == LINE:
            info(COMMAND_LOG, item[1])
        else:
            _, wall, cycle, values, logged = item
            facts = CommandFacts(*values)
            rows.append(as_row(facts(), wall, cycle))
            if logged:
                info(COMMAND_LOG, facts.log_line())
        if time.perf_counter() - start >= SLICE_S:
            os.sched_yield()  # a woken thread of the daemon runs now, not after a time slice
            start = time.perf_counter()
    return rows


def main(argv: list[str]) -> int:
    """`python -m ride_machine.service.adapters.history PATH MACHINE_ID SETTINGS_JSON LEVEL`: reads
    batches on stdin until it closes, then writes what it has and exits."""
    # The daemon decides when this process ends (it closes the pipe): a Ctrl-C or a TERM sent
    # to the daemon's process group must not cut the history short of the daemon's last events.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    name_os_thread("history")  # `top`, `ps -L`: not one more `python`
    path, machine_id, settings, level = argv
    pipe = _Pipe()
    setup_logging(level, stream=_LogStream(pipe))
    writer = _Writer(pipe, Path(path), machine_id, EventsSection.model_validate_json(settings))
    writer.start()
    try:
        for message in messages(0):
            tag = message[0]
            if tag == BATCH:
                writer.receive(_make(message[2]), message[1])
            elif tag == FLUSH:
                # No longer than the daemon waits: a locked disk must not keep this thread
                # from the pipe's end, which starts the stop (and its spill of the unwritten).
                writer.flush(timeout=float(message[2]))
                pipe.send([FLUSHED, message[1], writer.status()])
            elif tag == FAILED:
                writer.record_failure(message[1], message[2])
    finally:
        writer.close(timeout=10.0)
        flush_logs()
    return 0
