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

The file and its SQL are in service/adapters/eventdb.py, reading and the reader thread in
service/adapters/eventread.py, retention in service/adapters/retention.py.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

from schema.diag import EventsDiag
from schema.events import DroppedEvent, EventKind, EventPage, EventQuery, KnownDetails, StorageEvent
from service.adapters.eventdb import (
    BUSY_TIMEOUT_S,
    WRITER_WAIT_S,
    Row,
    StoredRow,
    as_row,
    claim_writer,
    connect,
    file_bytes,
    insert,
    open_log,
    stored,
)
from service.adapters.eventread import Reader
from service.adapters.retention import prune_and_vacuum
from service.adapters.unwritten import Unwritten
from service.config.model import EventsSection
from service.core.held import Held, LogLine
from service.threads import NamedThread

log = logging.getLogger(__name__)

EVENTS_FILE = "events.db"

COALESCE_S = 0.02
"""How long the writer gathers events after the first one before writing them in one batch."""

DEFER_MAX = 1024
"""Commands' held records (`defer`) queued at most: they are objects the garbage collector
scans, where a queued event is text; beyond this (a stalled disk) the scan thread makes them."""
STOP_BUSY_TIMEOUT_S = 0.2
"""Once stopping, how long a write waits for a database another process holds: the stop has a
deadline (the daemon ends the history process at it), and what is not written by then goes
into the file the next start writes (service/adapters/unwritten.py), safety events first."""

Listener = Callable[[list[StoredRow]], None]
"""Called with each committed batch, as stored (eventread's `row_event` makes a row an `Event`,
`row_payload` its wire bytes)."""


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


class EventLog:
    """The writer (and reader) of the event history; `emit` never blocks."""

    def __init__(
        self,
        path: Path,
        machine_id: str,
        settings: EventsSection,
        *,
        wall: Callable[[], float] = time.time,
        writer_wait_s: float = WRITER_WAIT_S,
    ) -> None:
        self.path = path
        self.writer_wait_s = writer_wait_s
        self._writer_fd: int | None = None
        """`claim_writer`'s lock, held while this writes the log."""
        self.machine_id = machine_id
        self.settings = settings
        self.wall = wall
        self.capacity = settings.queue_capacity
        self._items: deque[Row | Held | str] = deque()  # str: a log line (`defer`)
        self._deferred = 0
        """`Held` records among `_items`."""
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._hurry = threading.Event()
        """Set by a reader or `flush`: write what is queued now, without gathering more."""
        self._stopping = False
        self._listeners: list[Listener] = []
        self._conn: sqlite3.Connection | None = None
        self._writer: threading.Thread | None = None
        self._reader = Reader(
            path,
            machine_id,
            settings.page_max,
            stopping=lambda: self._stopping,
            catch_up=self._catch_up,
        )
        self.written = 0
        self.dropped = 0
        self.lost = 0
        self.failures = 0
        self.last_error: str | None = None
        self._dropped_recorded = 0
        self._failure: tuple[str, int] | None = None
        self._prune_due = 0.0
        self.previous_stop_clean: bool | None = None
        """Whether the last run in this log ended with a `daemon_stop` (None: empty log)."""
        self._unwritten = Unwritten(path)
        """The safety events a failed write left, kept across a stop (service/adapters/
        unwritten.py)."""

    # ------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the database and start the threads; a database that cannot be opened is
        reported (and its events counted as lost) but never stops the machine."""
        self._claim()
        self._open_or_replace()
        self._resume_unwritten()
        self._start_threads()

    def _resume_unwritten(self) -> None:
        """What the previous run could not write: its safety events first, then its lost count
        as a `storage_failed` event with the first write."""
        rows, lost, error = self._unwritten.resume()
        self.put_rows(rows)
        if lost:
            why = f"in the previous run: {error or 'events not written'}"
            if self._failure is not None:
                why, lost = f"{self._failure[0]}; {why}", lost + self._failure[1]
            self._failure = (why, lost)

    def _claim(self) -> None:
        """Wait for the log's previous writer to let go (`claim_writer`); said, not fatal."""
        self._writer_fd, busy = claim_writer(self.path, self.writer_wait_s)
        if busy is not None:
            log.error("event=events_writer_busy path=%s error=%r", self.path, busy)
            self.last_error = busy

    def _start_threads(self) -> None:
        self._writer = NamedThread(target=self._run, name="eventlog", daemon=True)
        self._writer.start()
        self._reader.start()

    def _open_or_replace(self) -> None:
        """Open the log (`open_log`): a file that is no event log is kept aside for a new one,
        which records that first; one that cannot open is said, its events counted as lost."""
        opened = open_log(self.path, self.wall())
        self._conn = opened.conn
        if opened.last_kind is not None:
            self.previous_stop_clean = opened.last_kind == EventKind.DAEMON_STOP
        if opened.aside is None:
            if opened.error is not None:
                self._fail(opened.error, 0)
            return
        error = (
            f"{self.path} was not a usable event log ({opened.error}); kept as {opened.aside.name}"
        )
        log.error(
            "event=events_db_set_aside path=%s aside=%s error=%r",
            self.path,
            opened.aside,
            opened.error,
        )
        self.failures += 1
        self.last_error = error
        self._failure = (error, 0)

    def close(self, timeout: float = 2.0) -> None:
        """Write what is queued, then stop both threads; never longer than `timeout` (a
        thread still waiting on a locked file is left behind, it is a daemon thread)."""
        deadline = time.monotonic() + timeout
        self._stop()
        if self._writer is not None:
            self._writer.join(max(0.0, deadline - time.monotonic()))
        self._reader.join(max(0.0, deadline - time.monotonic()))
        writer_done = self._writer is None or not self._writer.is_alive()
        if writer_done:
            self._spill()
        if self._conn is not None and writer_done:
            self._conn.close()
            self._conn = None
        if self._writer_fd is not None and writer_done:
            os.close(self._writer_fd)  # the next writer of this log may start
            self._writer_fd = None

    def _spill(self) -> None:
        """At the stop: what is unwritten (held safety events, events lost or dropped and not
        yet recorded) into the file the next start reads (service/adapters/unwritten.py)."""
        with self._lock:
            queued = without_lines(self._items)
            self._items.clear()
        rows = [item for item in queued if not isinstance(item, Held)]
        error, failed = self._failure or (None, 0)
        lost = self.dropped - self._dropped_recorded + len(queued) - len(rows) + failed
        lost += self._unwritten.hold(rows)
        self._unwritten.spill(lost, error or (f"{lost} events not written" if lost else None))

    def _stop(self) -> None:
        """No more events taken; the writer hurried to the end of the queue, the reader told
        to end."""
        with self._lock:
            self._stopping = True
        self._wake.set()
        self._hurry.set()
        self._reader.stop()

    def subscribe(self, listener: Listener) -> None:
        """Call `listener` (on the writer thread) with every batch once it is committed."""
        self._listeners.append(listener)

    # ---------------------------------------------------------------------------- emit
    def emit(self, details: KnownDetails, time: float, cycle: int | None) -> None:
        """Queue one event; when the queue is full it is dropped and counted, never waited on.

        Queued as plain text and numbers, which the garbage collector never scans: a queue
        filled by a stalled disk must not make the scan thread's collections longer."""
        row = as_row(details, time, cycle)
        with self._lock:
            if len(self._items) >= self.capacity or self._stopping:
                self.dropped += 1
                return
            self._items.append(row)
        if not self._wake.is_set():  # set() takes a Condition's lock: once per batch is enough
            self._wake.set()

    def put_rows(self, rows: Sequence[Row | str]) -> None:
        """Queue events already made, and log lines in their place, in order; events beyond
        the queue's capacity are dropped and counted, as `emit` does (lines, written now)."""
        with self._lock:
            room = 0 if self._stopping else max(0, self.capacity - len(self._items))
            self._items.extend(rows[:room])
            self.dropped += len(without_lines(rows[room:]))
        if not self._wake.is_set():
            self._wake.set()

    def defer(self, held: Held) -> bool:
        """Queue a command's held record, made (events, log line) on the writer thread in its
        place, off the command's and the scan thread's path; past `DEFER_MAX`, its events are
        made here and its line queued in its place. False (the caller makes it) before the
        writer runs, once it stops, or with the queue full."""
        with self._lock:
            if self._writer is None or self._stopping or len(self._items) >= self.capacity:
                return False
            queued = self._deferred < DEFER_MAX
            if queued:
                self._items.append(held)
                self._deferred += 1
        if not queued:
            self.put_rows(made_here(held))
        elif not self._wake.is_set():
            self._wake.set()
        return True

    def emit_now(self, details: KnownDetails, cycle: int | None = None) -> None:
        """An event from outside the scan loop, stamped with the wall clock and `cycle`."""
        self.emit(details, self.wall(), cycle)

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until everything queued so far is written (tests and shutdown)."""
        return self._drained(time.monotonic() + timeout, lambda: not self._items and not self._busy)

    def _drained(self, deadline: float, done: Callable[[], bool]) -> bool:
        """Hurry the writer, then wait until `done()` (read under the queue's lock), at most
        until `deadline`."""
        self._hurry.set()
        while True:
            with self._lock:
                if done():
                    return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.002)

    @property
    def queued(self) -> int:
        return len(self._items)

    def _unsettled(self) -> bool:
        """Events emitted but not yet written (or counted lost)."""
        return bool(self._items) or self._busy

    # ---------------------------------------------------------------------------- thread
    _busy = False

    def _take(self) -> list[Row]:
        """The next batch, held records made into its events in their place."""
        with self._lock:
            n = min(len(self._items), self.settings.batch_max)
            batch = [self._items.popleft() for _ in range(n)]
            self._busy = bool(batch) or self.dropped > self._dropped_recorded
            if not self._items:
                self._wake.clear()
            if self._deferred:
                self._deferred -= sum(isinstance(item, Held) for item in batch)
        rows: list[Row] = []
        for item in batch:
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

    def _gather(self, timeout: float) -> None:
        """Wait for the next event (at most `timeout`), then gather what follows for a moment
        (unless hurried): a write (and its publications) per event took the GIL from the Zenoh
        thread replying to the next command."""
        if self._wake.wait(timeout):
            self._hurry.wait(COALESCE_S)
        self._hurry.clear()

    def _run(self) -> None:
        while True:
            self._gather(min(1.0, self.settings.prune_every_s))
            batch: list[Row] = []
            failures = self.failures
            try:
                batch = self._take()
                # Held safety events are tried again every wait (at most 1 s), events or not.
                if batch or self.dropped > self._dropped_recorded or len(self._unwritten):
                    self._write(batch)
            except Exception as exc:  # noqa: BLE001 - one bad batch must not end the history
                self._fail(f"event writer failed: {exc!r}", len(batch), exc)
            finally:
                self._busy = False
            gave_up = self._stopping and self.failures > failures
            if self.wall() >= self._prune_due and not self._stopping:
                try:
                    self._prune()
                except Exception as exc:  # noqa: BLE001 - nor one bad prune
                    self._fail(f"event prune failed: {exc!r}", 0, exc)
            with self._lock:
                # A write that failed in the stop (a locked or full disk) is not tried again:
                # waiting on it would pass the stop's deadline, and the process killed there
                # spills nothing; `close` puts the rest, safety events kept, in the file.
                if self._stopping and (not self._items or gave_up):
                    return

    def _write(self, batch: list[Row]) -> None:
        now = self.wall()
        extra: list[KnownDetails] = []
        if self._failure is not None:
            error, lost = self._failure
            extra.append(StorageEvent(what="events", error=error, lost=lost))
        dropped = self.dropped - self._dropped_recorded
        if dropped:
            extra.append(DroppedEvent(count=dropped))
        held = self._unwritten.take()
        items = [as_row(d, now, None) for d in extra] + held + batch
        conn = self._conn
        if conn is None:
            conn = self._reopen()
        if conn is None:
            lost = self._unwritten.hold(held + batch)
            self._fail(self.last_error or "event log unavailable", lost)
            return
        machine_id = self.machine_id
        try:
            if self._stopping:
                conn.execute(f"PRAGMA busy_timeout = {int(STOP_BUSY_TIMEOUT_S * 1000)}")
            last = insert(conn, machine_id, items, self._pace)
        except sqlite3.Error as exc:
            # The safety record waits in memory for the next write; the rest is lost.
            self._fail(str(exc), self._unwritten.hold(held + batch))
            return
        self._failure = None
        self._dropped_recorded += dropped
        self.written += len(items)
        if self._listeners:
            self._publish(stored(last, machine_id, items))

    def _publish(self, rows: list[StoredRow]) -> None:
        """The rows just written, to every listener (on the writer's thread)."""
        for listener in self._listeners:
            try:
                listener(rows)
            except Exception as exc:  # noqa: BLE001 - a publishing failure loses no stored event
                log.warning("event=events_publish_failed error=%r", str(exc))

    def _pace(self) -> None:
        """Between two chunks of a batch's inserts: nothing here (the history's own process
        gives way to the daemon's threads, service/adapters/history_writer.py)."""

    def _fail(self, error: str, lost: int, exc: BaseException | None = None) -> None:
        """`lost` events not written: counted, recorded as `storage_failed` once writing works,
        and logged once per problem (`exc`: with its traceback, a bug rather than a disk)."""
        self.failures += 1
        self.lost += lost
        self.last_error = error
        ongoing = self._failure is not None and self._failure[0] == error
        total = lost + (self._failure[1] if self._failure is not None else 0)
        self._failure = (error, total)
        # Once per problem, not once per batch: a full disk must not also fill the log.
        # Every loss is counted in diag and recorded as `storage_failed` once writing works.
        (log.debug if ongoing else log.error)(
            "event=events_write_failed error=%r lost=%d", error, lost, exc_info=exc
        )

    def _reopen(self) -> sqlite3.Connection | None:
        try:
            self._conn = connect(self.path)
        except (sqlite3.Error, OSError) as exc:
            self.last_error = f"cannot open {self.path}: {exc}"
            return None
        return self._conn

    # ----------------------------------------------------------------------------- prune
    def _prune(self) -> None:
        """Drop what retention says (service/adapters/retention.py): routine events by age and
        the file's size, the safety record by its own age and size."""
        self._prune_due = self.wall() + self.settings.prune_every_s
        if self._conn is None:
            return
        try:
            prune_and_vacuum(self._conn, self.settings, self.wall(), self._write_queued)
        except sqlite3.Error as exc:
            log.warning("event=events_prune_failed error=%r", str(exc))

    def _write_queued(self) -> None:
        batch = self._take()
        if batch:
            self._write(batch)

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
