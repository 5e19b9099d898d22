"""The history process (`python -m ride_machine.service.adapters.history_writer`): makes the events
the daemon sends down the pipe and writes them with an `EventWriter` of its own, sending back
what it wrote, its counters and its log lines (service/adapters/history.py has the daemon's side).

It loads no pydantic: its settings are plain values, a command's event is made as JSON from
its facts (service/core/history/facts.py), and its own `storage_failed` and `events_dropped`
events too (service/adapters/eventdb.py). The wire models were half of its resident memory
(bench.rss_soak: 33 MiB with them); tests/service/adapters/test_history_footprint.py holds it so.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sqlite3
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from ride_machine.schema.event_kinds import EventKind
from ride_machine.service.core.history.facts import COMMAND_LOG, CommandFacts
from ride_machine.service.logfmt import flush_logs, info, setup_logging
from ride_machine.service.threads import name_os_thread

from .eventdb import WRITER_WAIT_S, Row, StoredRow
from .eventwriter import EventWriter
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
from .writer_thread import WriterThread

SLICE_S = 0.0001
"""The history process gives way (`sched_yield`) after this much work at a time."""
COMMAND = EventKind.COMMAND._value_


class WriterSettings(NamedTuple):
    """`[events]` as the history process reads it: plain values taken by name from the daemon's
    `EventsSection` (its JSON, checked there). A tuple: no `dataclasses` (its `inspect` is
    1.3 MiB resident) in this process."""

    queue_capacity: int
    batch_max: int
    max_age_days: float
    max_mb: float
    safety_max_age_days: float
    safety_max_mb: float
    prune_every_s: float

    @classmethod
    def from_json(cls, text: str) -> WriterSettings:
        values = json.loads(text)
        return cls(**{name: values[name] for name in cls._fields})


class _Pipe:
    """Messages to the daemon on this process's stdout, from any of its threads."""

    def __init__(self) -> None:
        self._out = os.fdopen(1, "wb", buffering=0, closefd=False)
        self._lock = threading.Lock()

    def send(self, message: list[Any]) -> None:
        """One message; to a daemon that is gone (killed), none: what it sent before it went is
        still read and written, and the pipe's end ends this process."""
        data = encode(message)
        with self._lock, contextlib.suppress(BrokenPipeError):
            write_all(self._out, data)


class _LogStream:
    """Where the log writer of the history process writes: back to the daemon."""

    def __init__(self, pipe: _Pipe) -> None:
        self.pipe = pipe

    def write(self, text: str) -> None:
        self.pipe.send([LOG, text])

    def flush(self) -> None:
        pass


class _Writer(WriterThread[WriterSettings]):
    """The daemon's batches, queued and written by a thread of this process as `EventLog`'s
    are in the daemon (`WriterThread`); after each write, its rows and counters go back."""

    def __init__(
        self,
        pipe: _Pipe,
        path: Path,
        machine_id: str,
        settings: WriterSettings,
        *,
        wall: Callable[[], float] = time.time,
    ) -> None:
        super().__init__()
        self.pipe = pipe
        self.settings = settings
        self.wall = wall
        # Between a batch's chunks of inserts it gives way, as `make_rows` does between events.
        self.writer = EventWriter(self, path, machine_id, settings, os.sched_yield)
        self.received = 0
        self.forwarded = 0
        """Of `dropped`, those the daemon dropped (it counts them itself)."""
        self._wrote: list[StoredRow] = []
        self.writer.listeners.append(self._wrote.extend)
        self._in_flight = 0
        """Rows of the batch being written."""
        self._own = 0
        """Events of its own queued at the start (the previous run's unwritten), which the
        daemon never sent: not in `received`, but in the queue until written."""
        self._again: set[Row] = set()
        """Events sent again (`receive`), not written yet: a process that ended may have."""

    def start(self) -> None:
        """Claim and open the log (the daemon has set aside a file that is none), queue what
        the last run left unwritten, and start the writer thread."""
        self.writer.claim(WRITER_WAIT_S)
        self.writer.open_or_replace(self.wall())
        self._queue(self.writer.resume_unwritten())
        self._own = len(self._items)  # queued before any of the daemon's
        self._start_writing()

    def close(self, timeout: float = 2.0) -> None:
        """Write what is queued and stop, within `timeout`; what is left is spilled."""
        self._stop_taking()
        if self._join(time.monotonic() + timeout):
            self._spill(self._take_all())

    def receive(self, rows: list[Row], dropped: int, again: int = 0) -> None:
        """A batch of the daemon's; its first `again` rows were sent to a process that ended
        before it confirmed them."""
        with self._lock:
            self.received += len(rows)
            self.dropped += dropped
            self.forwarded += dropped
            self._again.update(rows[:again])
        self._queue(rows)

    def _queue(self, rows: list[Row]) -> None:
        """Rows beyond the queue's capacity are dropped and counted, as `EventLog` does (the
        safety record's with a reserve: the daemon's queue kept them)."""
        self._admit(rows, self.settings.queue_capacity)

    def record_failure(self, error: str, lost: int) -> None:
        """A failure the daemon saw (an earlier process ended): written with the next batch."""
        with self._lock:
            self.writer.failure = (error, lost)

    def status(self) -> list[Any]:
        """Its counters, and how many of the daemon's events are settled: written, dropped or
        counted lost (those neither queued nor in the batch being written)."""
        with self._lock:
            settled = self.received + self._own - len(self._items) - self._in_flight
            own_dropped = self.dropped - self.forwarded
        return [self.written, self.lost, self.failures, self.last_error, own_dropped, settled]

    # ---------------------------------------------------------------------------- thread
    def _taken(self, batch: list[Row]) -> None:
        self._in_flight = len(batch)

    def _write(self, batch: list[Row]) -> None:
        if self._again:
            batch = self._not_stored(batch)
        super()._write(batch)
        self._in_flight = 0
        rows, self._wrote[:] = list(self._wrote), []
        # A daemon killed before this write: the rows are stored all the same (not lost), and
        # the end of its pipe ends this process.
        self.pipe.send([WROTE, rows, self.status()])

    def _not_stored(self, batch: list[Row]) -> list[Row]:
        """`batch` less the events sent again that are stored already: a process killed after
        its write and before its word back wrote them (a duplicate E-stop would read as two)."""
        with self._lock:
            again = [row for row in batch if row in self._again]
            self._again.difference_update(again)
        conn = self.writer.conn
        stored = {row for row in again if conn is not None and _stored(conn, row)}
        return [row for row in batch if row not in stored] if stored else batch


def _stored(conn: sqlite3.Connection, row: Row) -> bool:
    """Whether the log holds `row` (same kind, details, time and cycle); False when it cannot
    tell (then the write that follows fails as well, and holds it)."""
    kind, details, wall, cycle = row
    try:
        found = conn.execute(
            "SELECT 1 FROM events WHERE time = ? AND kind = ? AND details = ? AND cycle IS ?"
            " LIMIT 1",
            (wall, kind, details, cycle),
        ).fetchall()
    except sqlite3.Error:
        return False
    return bool(found)


def make_rows(items: Sequence[Item]) -> list[Row]:
    """A batch's events as rows; a command's event and its log line made here (and, for what
    no process took, in the daemon at its stop)."""
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
            rows.append((COMMAND, facts.details(), wall, cycle))
            if logged:
                info(COMMAND_LOG, facts.log_line())
        if time.perf_counter() - start >= SLICE_S:
            os.sched_yield()  # a woken thread of the daemon runs now, not after a time slice
            start = time.perf_counter()
    return rows


def main(argv: list[str]) -> int:
    """`python -m ride_machine.service.adapters.history_writer PATH MACHINE_ID SETTINGS_JSON
    LEVEL`: reads batches on stdin until it closes, then writes what it has and exits."""
    # The daemon decides when this process ends (it closes the pipe): a Ctrl-C or a TERM sent
    # to the daemon's process group must not cut the history short of the daemon's last events.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    name_os_thread("history")  # `top`, `ps -L`: not one more `python`
    path, machine_id, settings, level = argv
    pipe = _Pipe()
    setup_logging(level, stream=_LogStream(pipe))
    writer = _Writer(pipe, Path(path), machine_id, WriterSettings.from_json(settings))
    writer.start()
    # Its first word: the daemon, which waits for it longer than for one that has started (a
    # loaded host starts an interpreter slowly), from now on calls a silence a stall.
    pipe.send([WROTE, [], writer.status()])
    try:
        for message in messages(0):
            tag = message[0]
            if tag == BATCH:
                writer.receive(make_rows(message[2]), message[1], message[3])
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


if __name__ == "__main__":
    code = main(sys.argv[1:])
    os._exit(code)  # everything is written: no interpreter teardown for the daemon to wait on
