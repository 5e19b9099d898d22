"""The event history on disk: SQLite (WAL) in `<data_dir>/events.db`, written off the scan thread.

`EventLog.emit` only appends to a bounded queue (a full queue counts the event as dropped; the
count is written as an `events_dropped` event once there is room again). One writer thread
inserts what is queued in one transaction per batch, hands the written events to listeners (the
bus publishes them), and prunes by age and size between batches. A reader thread answers
queries, so neither Zenoh's callback thread nor the scan thread ever waits on the disk.

Crash safety: WAL with `synchronous=NORMAL` keeps every committed batch across a killed
process (a power cut may lose the last batches, never the database). What a SIGKILL loses is
what was still queued or in the batch being written: at most `queue_capacity + batch_max`
events, in practice the last millisecond or so (tests/service/adapters/test_eventlog_crash.py
measures it).

This module is the façade the daemon and the bus call, with the queue and the writer thread;
what a batch does to the database (and a failed write's accounting) is the writer's,
service/adapters/eventwriter.py. The file and its SQL are in service/adapters/eventdb.py, reading
and the reader thread in service/adapters/eventread.py, retention in
service/adapters/retention.py.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from ride_machine.schema.codec import dump_json
from ride_machine.schema.diag import EventsDiag
from ride_machine.schema.events import EventPage, EventQuery, KnownDetails
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.held import Held, LogLine

from .eventdb import BUSY_TIMEOUT_S, WRITER_WAIT_S, Row, file_bytes
from .eventread import Reader
from .eventwriter import EventWriter, Listener
from .writer_thread import WriterThread

log = logging.getLogger(__name__)

EVENTS_FILE = "events.db"

DEFER_MAX = 1024
"""Commands' held records (`defer`) queued at most: they are objects the garbage collector
scans, where a queued event is text; beyond this (a stalled disk) the scan thread makes them."""


def as_row(details: KnownDetails, wall: float, cycle: int | None) -> Row:
    """An event as it is queued and written."""
    return (details.kind, dump_json(details), wall, cycle)


def made_here(held: Held) -> list[Row | str]:
    """A held record made on the caller's thread: its events as rows, then its command's log
    line as text, to be written in its place (any other `then` is called now)."""
    line, held.then = held.then, None
    rows: list[Row | str] = []
    held.write(lambda details, wall, cycle: rows.append(as_row(details, wall, cycle)))
    if isinstance(line, LogLine):
        rows.append(line.facts.log_line())
    elif line is not None:
        line()
    return rows


def without_lines(items: Sequence[Row | Held | str]) -> list[Row | Held]:
    """`items` less the log lines among them, which are written now (late, but not lost)."""
    for item in items:
        if isinstance(item, str):
            LogLine.write(item)
    return [item for item in items if not isinstance(item, str)]


class EventLog(WriterThread[EventsSection]):
    """The event history as the daemon and the bus use it: `emit` never blocks; a writer thread
    (`WriterThread`) hands what is queued to the `EventWriter`, a reader thread answers
    queries."""

    def __init__(
        self,
        path: Path,
        machine_id: str,
        settings: EventsSection,
        *,
        wall: Callable[[], float] = time.time,
        writer_wait_s: float = WRITER_WAIT_S,
        pace: Callable[[], None] | None = None,
    ) -> None:
        super().__init__()
        self.path = path
        self.machine_id = machine_id
        self.settings = settings
        self.wall = wall
        self.capacity = settings.queue_capacity
        self.writer_wait_s = writer_wait_s
        self.writer = EventWriter(self, path, machine_id, settings, pace)
        """What a batch does to the database; it counts in `WriterThread`'s attributes."""
        # `_items`: rows, `Held` records (`defer`) and log lines (str) in their place.
        self._deferred = 0
        """`Held` records among `_items`."""
        self._reader = Reader(
            path,
            machine_id,
            settings.page_max,
            stopping=lambda: self._stopping,
            catch_up=self._catch_up,
        )
        self.previous_stop_clean: bool | None = None
        """Whether the last run in this log ended with a `daemon_stop` (None: empty log)."""

    # ------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the database and start the threads; a database that cannot be opened is
        reported (and its events counted as lost) but never stops the machine."""
        self.writer.claim(self.writer_wait_s)
        self.previous_stop_clean = self.writer.open_or_replace(self.wall())
        self.put_rows(self.writer.resume_unwritten())
        self._start_threads()

    def _start_threads(self) -> None:
        self._start_writing()
        self._reader.start()

    def close(self, timeout: float = 2.0) -> None:
        """Write what is queued, then stop both threads; never longer than `timeout` (a
        thread still waiting on a locked file is left behind, it is a daemon thread)."""
        deadline = time.monotonic() + timeout
        self._stop()
        ended = self._join(deadline)
        self._reader.join(max(0.0, deadline - time.monotonic()))
        if ended:
            self._spill(without_lines(self._take_all()))

    def _stop(self) -> None:
        """No more events taken; the writer hurried to the end of the queue, the reader told
        to end."""
        self._stop_taking()
        self._reader.stop()

    def subscribe(self, listener: Listener) -> None:
        """Call `listener` (on the writer thread) with every batch once it is committed."""
        self.writer.listeners.append(listener)

    # ---------------------------------------------------------------------------- emit
    def emit(self, details: KnownDetails, time: float, cycle: int | None) -> None:
        """Queue one event; when the queue is full it is dropped and counted, never waited on.
        An event of the safety record (an E-stop, a fault, a watchdog trip) may go
        `SAFETY_RESERVE` past a queue that routine events filled: a flood of commands during
        a stalled disk or history process does not take the record of the E-stop with it.

        Queued as plain text and numbers, which the garbage collector never scans: a queue
        filled by a stalled disk must not make the scan thread's collections longer."""
        self._admit((as_row(details, time, cycle),), self.capacity)

    def put_rows(self, rows: Sequence[Row | str]) -> None:
        """Queue events already made, and log lines in their place, in order; events beyond
        the queue's capacity are dropped and counted, as `emit` does."""
        self._admit(rows, self.capacity)

    def defer(self, held: Held) -> bool:
        """Queue a command's held record, made (events, log line) on the writer thread in its
        place, off the command's and the scan thread's path; past `DEFER_MAX`, its events are
        made here and its line queued in its place. False (the caller makes it) before the
        writer runs, once it stops, or with the queue full."""
        with self._lock:
            if self._thread is None or self._stopping or len(self._items) >= self.capacity:
                return False
            queued = self._deferred < DEFER_MAX
            if queued:
                self._items.append(held)
                self._deferred += 1
        if not queued:
            self.put_rows(made_here(held))
        else:
            self._wake_writer()
        return True

    def emit_now(self, details: KnownDetails, cycle: int | None = None) -> None:
        """An event from outside the scan loop, stamped with the wall clock and `cycle`."""
        self.emit(details, self.wall(), cycle)

    @property
    def queued(self) -> int:
        return len(self._items)

    def _unsettled(self) -> bool:
        """Events emitted but not yet written (or counted lost)."""
        return bool(self._items) or self._busy

    # ---------------------------------------------------------------------------- thread
    def _taken(self, batch: list[Row | Held | str]) -> None:
        if self._deferred:
            self._deferred -= sum(isinstance(item, Held) for item in batch)

    def _take(self) -> list[Row]:
        """The next batch, held records made into its events in their place."""
        rows: list[Row] = []
        for item in self._pop_batch():
            if isinstance(item, Held):
                self._make(item, rows)
            elif isinstance(item, str):
                LogLine.write(item)
            else:
                rows.append(item)
        return rows

    def _make(self, held: Held, rows: list[Row]) -> None:
        """A held record's events into `rows` (and its log line written)."""

        def add(details: KnownDetails, time: float, cycle: int | None) -> None:
            rows.append(as_row(details, time, cycle))

        try:
            held.write(add)
        except Exception as exc:  # one bad record must not stop the writer
            self.lost += 1
            log.error("event=events_make_failed error=%r", str(exc), exc_info=exc)

    # ----------------------------------------------------------------------------- reads
    def read(
        self, q: EventQuery, respond: Callable[[EventPage], None], fail: Callable[[str], None]
    ) -> bool:
        """Answer `q` on the reader thread (`fail` with the reason if the database cannot be
        read); False, and nothing queued, when the reader is busy."""
        return self._reader.read(q, respond, fail)

    def _catch_up(self) -> None:
        """Before a read: what was emitted before it written (for at most the busy timeout)."""
        if self._unsettled():
            self.flush(BUSY_TIMEOUT_S)

    def diag(self) -> EventsDiag:
        return EventsDiag(
            written=self.written,
            queued=self.queued,
            dropped=self.dropped,
            lost=self.lost,
            failures=self.failures,
            last_error=self.last_error,
            file_bytes=file_bytes(self.path),
        )
