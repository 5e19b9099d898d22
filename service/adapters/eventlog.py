"""The event history on disk: SQLite (WAL) in `<data_dir>/events.db`, written off the scan thread.

`EventLog.emit` only appends to a bounded queue (a full queue counts the event as dropped; the
count is written as an `events_dropped` event once there is room again). One writer thread
inserts what is queued in one transaction per batch, hands the written events to listeners (the
bus publishes them), and prunes by age and size between batches. A reader thread answers
queries, so neither Zenoh's callback thread nor the scan thread ever waits on the disk.

Crash safety: WAL with `synchronous=NORMAL` keeps every committed batch across a killed
process (a power cut may lose the last batches, never the database). What a SIGKILL loses is
what was still queued or in the batch being written: at most `queue_capacity + batch_max`
events, in practice the last millisecond or so (tests/service/test_eventlog_crash.py measures it).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import queue
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from schema.codec import dump_json, pack
from schema.diag import EventsDiag
from schema.events import (
    DroppedEvent,
    Event,
    EventKind,
    EventPage,
    EventQuery,
    KnownDetails,
    StorageEvent,
)
from service.adapters.retention import prune
from service.adapters.unwritten import Unwritten
from service.config.model import EventsSection
from service.core.events import Held
from service.threads import NamedThread

log = logging.getLogger(__name__)

EVENTS_FILE = "events.db"
MAX_PAGE_BYTES = 256 * 1024
"""A reply page stops growing past this many bytes of event JSON (and says `more`)."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    cycle INTEGER,
    machine_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    details TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS events_time ON events(time);
CREATE INDEX IF NOT EXISTS events_kind ON events(kind, seq);
"""


_TABLE_COLUMNS = ["seq", "time", "cycle", "machine_id", "kind", "details"]
_INSERT = "INSERT INTO events (time, cycle, machine_id, kind, details) VALUES (?, ?, ?, ?, ?)"

BUSY_TIMEOUT_S = 1.0
"""How long a write or read waits for a database another process holds locked before it
counts as failed: short, so a locked file can never hold up start-up or the shutdown deadline."""


WRITER_WAIT_S = 5.0
"""How long a log's writer waits at start for the one before it to let go (`claim_writer`):
the history process of a killed daemon still writes what it was sent, for milliseconds."""
WRITER_POLL_S = 0.01


COALESCE_S = 0.02
"""How long the writer gathers events after the first one before writing them in one batch."""

WRITE_CHUNK = 16
"""Rows inserted per `executemany` of a batch (all in its one transaction), `_pace` between."""

DEFER_MAX = 1024
"""Commands' held records (`defer`) queued at most: they are objects the garbage collector
scans, where a queued event is text; beyond this (a stalled disk) the scan thread makes them."""


class ForeignDatabase(sqlite3.DatabaseError):
    """A SQLite file whose `events` table is not ours (another program's, or an old layout)."""


# ---------------------------------------------------------------------------------- reading
def connect(path: Path) -> sqlite3.Connection:
    """A connection in WAL mode with the table in place (creating the file if needed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    conn = sqlite3.connect(
        path, timeout=BUSY_TIMEOUT_S, check_same_thread=False, isolation_level=None
    )
    try:
        columns = [row[1] for row in conn.execute("PRAGMA table_info(events)").fetchall()]
        if columns and columns != _TABLE_COLUMNS:
            raise ForeignDatabase(f"its events table has the columns {columns}")
        # auto_vacuum must be chosen before the first table exists; later it is a no-op.
        conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=NORMAL")
        conn.execute("PRAGMA journal_size_limit=4194304")
        conn.executescript(_SCHEMA)
    except BaseException:
        conn.close()
        raise
    return conn


def claim_writer(path: Path, wait_s: float) -> tuple[int | None, str | None]:
    """One writer per log: an exclusive `flock` on `<path>.writer`, which holds the holder's
    pid, waited for up to `wait_s`. The file descriptor (closed: let go), and None or, when
    another process still holds it after the wait, who does (the log is written anyway, so
    that no event is lost, and that is said). (None, None) where no lock file can be made."""
    lock = path.with_name(path.name + ".writer")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError:
        return None, None  # a read-only place: writing will say what is wrong
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pass  # held: wait, below
        except OSError:  # a file system without locks (ENOLCK): written unlocked, as before
            os.close(fd)
            return None, None
        else:
            with contextlib.suppress(OSError):  # a full disk: held all the same, only unnamed
                os.ftruncate(fd, 0)
                os.pwrite(fd, str(os.getpid()).encode(), 0)
            return fd, None
        if time.monotonic() < deadline:
            time.sleep(WRITER_POLL_S)
            continue
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        return None, (
            f"{path} is still written by another process (pid {holder}) after"
            f" {wait_s:g} s; writing beside it, so events of the two may interleave"
        )


def unusable(exc: BaseException) -> bool:
    """Whether `exc` says the file is not a usable event log at all (garbage, a damaged
    image, another schema), as opposed to a passing problem (locked, disk full, read-only)."""
    return isinstance(exc, sqlite3.DatabaseError) and not isinstance(exc, sqlite3.OperationalError)


def set_aside(path: Path, stamp: float) -> Path:
    """Rename an unusable log (with its WAL and shared-memory files) out of the way, kept for
    whoever wants to look at it: `events.db.bad-<UTC time>`."""
    suffix = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(stamp))
    aside = path.with_name(f"{path.name}.bad-{suffix}")
    n = 1
    while aside.exists():
        n += 1
        aside = path.with_name(f"{path.name}.bad-{suffix}-{n}")
    os.rename(path, aside)
    for extra in ("-wal", "-shm"):
        with contextlib.suppress(FileNotFoundError):
            os.rename(f"{path}{extra}", f"{aside}{extra}")
    return aside


def connect_readonly(path: Path) -> sqlite3.Connection:
    """Read an existing log (the offline export); never creates or changes the file."""
    if not path.is_file():
        raise FileNotFoundError(f"no event log at {path}")
    return sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0, check_same_thread=False)


StoredRow = tuple[int, float, int | None, str, str, str]
"""An event as stored: seq, time, cycle, machine_id, kind, and its details as JSON text."""


def row_event(row: StoredRow) -> Event:
    return Event.model_validate(_row_fields(row))


def row_payload(row: StoredRow) -> bytes:
    """The msgpack bytes of `row_event(row)` (`encode`'s), made from the stored row without
    building the model: the writer publishes every event it commits, one per command under a
    command stream, and the model's validation and serialisation were most of that work."""
    return pack(_row_fields(row))


def _row_fields(row: StoredRow) -> dict[str, Any]:
    """A stored row as the `Event`'s fields, in the model's order (its wire order)."""
    seq, when, cycle, machine_id, kind, details = row
    return {
        "seq": seq,
        "time": when,
        "cycle": cycle,
        "machine_id": machine_id,
        "kind": kind,
        "details": json.loads(details),
    }


def _where(q: EventQuery) -> tuple[str, list[object]]:
    clauses: list[str] = []
    args: list[object] = []
    for column, op, value in (
        ("seq", ">=", q.since),
        ("seq", "<=", q.until),
        ("time", ">=", q.since_time),
        ("time", "<=", q.until_time),
    ):
        if value is not None:
            clauses.append(f"{column} {op} ?")
            args.append(value)
    if q.kinds:
        clauses.append(f"kind IN ({','.join('?' * len(q.kinds))})")
        args.extend(q.kinds)
    return (" WHERE " + " AND ".join(clauses)) if clauses else "", args


_COLUMNS = "SELECT seq, time, cycle, machine_id, kind, details FROM events"


def read_page(conn: sqlite3.Connection, machine_id: str, q: EventQuery, page_max: int) -> EventPage:
    """One bounded page: at most `page_max` events and about `MAX_PAGE_BYTES` of them."""
    where, args = _where(q)
    limit = min(q.limit or page_max, page_max)
    if q.last is not None:
        n = min(q.last, page_max)
        rows = conn.execute(f"{_COLUMNS}{where} ORDER BY seq DESC LIMIT ?", [*args, n]).fetchall()
        rows.reverse()
        more = False
    else:
        sql = f"{_COLUMNS}{where} ORDER BY seq LIMIT ?"
        rows = conn.execute(sql, [*args, limit + 1]).fetchall()
        more = len(rows) > limit
        rows = rows[:limit]
    events: list[Event] = []
    size = 0
    for row in rows:
        size += len(row[5]) + 64
        if events and size > MAX_PAGE_BYTES:
            more = True
            break
        events.append(row_event(row))
    [(first, last)] = conn.execute("SELECT MIN(seq), MAX(seq) FROM events").fetchall()
    next_since = events[-1].seq + 1 if more and events else None
    return EventPage(
        machine_id=machine_id,
        events=events,
        more=more,
        next_since=next_since,
        first_seq=first,
        last_seq=last,
    )


def iter_events(conn: sqlite3.Connection, q: EventQuery, chunk: int = 1000) -> Iterator[Event]:
    """Every matching event, oldest first, read in chunks (the offline export)."""
    since = q.since
    while True:
        page_q = EventQuery(
            since=since,
            until=q.until,
            since_time=q.since_time,
            until_time=q.until_time,
            kinds=q.kinds,
        )
        where, args = _where(page_q)
        rows = conn.execute(f"{_COLUMNS}{where} ORDER BY seq LIMIT ?", [*args, chunk]).fetchall()
        for row in rows:
            yield row_event(row)
        if len(rows) < chunk:
            return
        since = rows[-1][0] + 1


# ---------------------------------------------------------------------------------- writing
Listener = Callable[[list[StoredRow]], None]
"""Called with each committed batch, as stored (`row_event` makes a row an `Event`, `row_payload`
its wire bytes)."""


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
        self._items: deque[_Row | Held] = deque()
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
        self._reads: queue.Queue[_ReadJob] = queue.Queue(maxsize=32)
        self._reader: threading.Thread | None = None
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
        self._reader = NamedThread(target=self._serve_reads, name="eventlog-read", daemon=True)
        self._reader.start()

    def _open_or_replace(self) -> None:
        try:
            self._open()
        except (sqlite3.Error, OSError) as exc:
            self._conn = None
            if unusable(exc):
                self._replace(exc)
            else:
                self._fail(f"cannot open {self.path}: {exc}", 0)

    def _open(self) -> None:
        self._conn = connect(self.path)
        # fetchall: a cursor left open would hold a read transaction for good.
        last = "SELECT kind FROM events ORDER BY seq DESC LIMIT 1"
        rows = self._conn.execute(last).fetchall()
        if rows:
            self.previous_stop_clean = rows[0][0] == EventKind.DAEMON_STOP

    def _replace(self, exc: BaseException) -> None:
        """Keep an unusable file aside and start a new log, recorded as its first event."""
        try:
            aside = set_aside(self.path, self.wall())
            self._open()
        except (sqlite3.Error, OSError) as again:
            self._conn = None
            self._fail(f"cannot open {self.path}: {exc}; cannot replace it: {again}", 0)
            return
        error = f"{self.path} was not a usable event log ({exc}); kept as {aside.name}"
        log.error("event=events_db_set_aside path=%s aside=%s error=%r", self.path, aside, str(exc))
        self.failures += 1
        self.last_error = error
        self._failure = (error, 0)

    def close(self, timeout: float = 2.0) -> None:
        """Write what is queued, then stop both threads; never longer than `timeout` (a
        thread still waiting on a locked file is left behind, it is a daemon thread)."""
        deadline = time.monotonic() + timeout
        self._stop()
        for thread in (self._writer, self._reader):
            if thread is not None:
                thread.join(max(0.0, deadline - time.monotonic()))
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
            queued = list(self._items)
            self._items.clear()
        lost = self.dropped - self._dropped_recorded
        lost += self._unwritten.hold([item for item in queued if not isinstance(item, Held)])
        lost += sum(isinstance(item, Held) for item in queued)
        error = None
        if self._failure is not None:
            error, failed = self._failure
            lost += failed
        self._unwritten.spill(lost, error or (f"{lost} events not written" if lost else None))

    def _stop(self) -> None:
        """No more events taken; the writer hurried to the end of the queue, the reader told
        to end."""
        with self._lock:
            self._stopping = True
        self._wake.set()
        self._hurry.set()
        if self._reader is not None:
            with contextlib.suppress(queue.Full):
                self._reads.put_nowait(lambda conn, error: None)

    def subscribe(self, listener: Listener) -> None:
        """Call `listener` (on the writer thread) with every batch once it is committed."""
        self._listeners.append(listener)

    # ---------------------------------------------------------------------------- emit
    def emit(self, details: KnownDetails, time: float, cycle: int | None) -> None:
        """Queue one event; when the queue is full it is dropped and counted, never waited on.

        Queued as plain text and numbers, which the garbage collector never scans: a queue
        filled by a stalled disk must not make the scan thread's collections longer."""
        row = _row(details, time, cycle)
        with self._lock:
            if len(self._items) >= self.capacity or self._stopping:
                self.dropped += 1
                return
            self._items.append(row)
        if not self._wake.is_set():  # set() takes a Condition's lock: once per batch is enough
            self._wake.set()

    def put_rows(self, rows: list[_Row]) -> None:
        """Queue events already made (kind, details JSON, wall time, cycle), in order; those
        beyond the queue's capacity are dropped and counted, as `emit` does."""
        with self._lock:
            room = 0 if self._stopping else max(0, self.capacity - len(self._items))
            self._items.extend(rows[:room])
            self.dropped += max(0, len(rows) - room)
        if not self._wake.is_set():
            self._wake.set()

    def defer(self, held: Held) -> bool:
        """Queue a command's held record, made (events and log line) on the writer thread in
        its place among the events: a command stream's events are made off both the command's
        and the scan thread's path. False (made by the caller, its events queued or counted as
        dropped as any) before the writer runs, once it stops, or with the queue full."""
        with self._lock:
            if (
                self._writer is None
                or self._stopping
                or len(self._items) >= self.capacity
                or self._deferred >= DEFER_MAX
            ):
                return False
            self._items.append(held)
            self._deferred += 1
        if not self._wake.is_set():
            self._wake.set()
        return True

    def emit_now(self, details: KnownDetails) -> None:
        """An event from outside the scan loop, stamped with the wall clock."""
        self.emit(details, self.wall(), None)

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

    def _take(self) -> list[_Row]:
        """The next batch, held records made into its events in their place."""
        with self._lock:
            n = min(len(self._items), self.settings.batch_max)
            batch = [self._items.popleft() for _ in range(n)]
            self._busy = bool(batch) or self.dropped > self._dropped_recorded
            if not self._items:
                self._wake.clear()
            if self._deferred:
                self._deferred -= sum(isinstance(item, Held) for item in batch)
        rows: list[_Row] = []
        for item in batch:
            if isinstance(item, Held):
                self._make(item, rows)
            else:
                rows.append(item)
        return rows

    def _make(self, held: Held, rows: list[_Row]) -> None:
        """A held record's events into `rows` (and its log line written)."""

        def add(details: KnownDetails, time: float, cycle: int | None) -> None:
            rows.append(_row(details, time, cycle))

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
            batch: list[_Row] = []
            try:
                batch = self._take()
                # Held safety events are tried again every wait (at most 1 s), events or not.
                if batch or self.dropped > self._dropped_recorded or len(self._unwritten):
                    self._write(batch)
            except Exception as exc:  # noqa: BLE001 - one bad batch must not end the history
                self._fail(f"event writer failed: {exc!r}", len(batch), exc)
            finally:
                self._busy = False
            if self.wall() >= self._prune_due:
                try:
                    self._prune()
                except Exception as exc:  # noqa: BLE001 - nor one bad prune
                    self._fail(f"event prune failed: {exc!r}", 0, exc)
            with self._lock:
                if self._stopping and not self._items:
                    return

    def _write(self, batch: list[_Row]) -> None:
        now = self.wall()
        extra: list[KnownDetails] = []
        if self._failure is not None:
            error, lost = self._failure
            extra.append(StorageEvent(what="events", error=error, lost=lost))
        dropped = self.dropped - self._dropped_recorded
        if dropped:
            extra.append(DroppedEvent(count=dropped))
        held = self._unwritten.take()
        items = [_row(d, now, None) for d in extra] + held + batch
        conn = self._conn
        if conn is None:
            conn = self._reopen()
        if conn is None:
            lost = self._unwritten.hold(held + batch)
            self._fail(self.last_error or "event log unavailable", lost)
            return
        machine_id = self.machine_id
        try:
            conn.execute("BEGIN")
            for at in range(0, len(items), WRITE_CHUNK):
                chunk = items[at : at + WRITE_CHUNK]
                conn.executemany(_INSERT, [(w, c, machine_id, k, d) for k, d, w, c in chunk])
                self._pace()
            # One transaction holds the write lock: AUTOINCREMENT numbered the batch in a row.
            [(last,)] = conn.execute("SELECT last_insert_rowid()").fetchall()
            conn.execute("COMMIT")
        except sqlite3.Error as exc:
            if conn.in_transaction:
                with contextlib.suppress(sqlite3.Error):  # the disk that failed the write
                    conn.execute("ROLLBACK")
            # The safety record waits in memory for the next write; the rest is lost.
            self._fail(str(exc), self._unwritten.hold(held + batch))
            return
        self._failure = None
        self._dropped_recorded += dropped
        self.written += len(items)
        if not self._listeners:
            return
        first = last - len(items) + 1
        rows: list[StoredRow] = [
            (first + i, when, cycle, machine_id, kind, details)
            for i, (kind, details, when, cycle) in enumerate(items)
        ]
        for listener in self._listeners:
            try:
                listener(rows)
            except Exception as exc:  # noqa: BLE001 - a publishing failure loses no stored event
                log.warning("event=events_publish_failed error=%r", str(exc))

    def _pace(self) -> None:
        """Between two chunks of a batch's inserts: nothing here (the history's own process
        gives way to the daemon's threads, service/adapters/history.py)."""

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
        conn = self._conn
        if conn is None:
            return
        try:
            prune(conn, self.settings, self.wall(), self._write_queued)
            conn.execute("PRAGMA incremental_vacuum")
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        except sqlite3.Error as exc:
            log.warning("event=events_prune_failed error=%r", str(exc))

    def _write_queued(self) -> None:
        batch = self._take()
        if batch:
            self._write(batch)

    def file_bytes(self) -> int:
        """The database file and its WAL on disk."""
        total = 0
        for suffix in ("", "-wal"):
            with contextlib.suppress(OSError):  # not there (yet): counts as empty
                total += os.path.getsize(f"{self.path}{suffix}")
        return total

    # ----------------------------------------------------------------------------- reads
    def read(
        self, q: EventQuery, respond: Callable[[EventPage], None], fail: Callable[[str], None]
    ) -> bool:
        """Answer `q` on the reader thread (`fail` with the reason if the database cannot be
        read); False, and nothing queued, when the reader is busy."""

        def job(conn: sqlite3.Connection | None, error: str | None) -> None:
            if conn is None:
                fail(error or "event log unavailable")
                return
            try:
                page = read_page(conn, self.machine_id, q, self.settings.page_max)
            except Exception as exc:  # noqa: BLE001 - the reader thread must answer the next query too
                fail(f"event log read failed: {exc}")
                return
            respond(page)

        try:
            self._reads.put_nowait(job)
        except queue.Full:
            return False
        return True

    def _serve_reads(self) -> None:
        conn: sqlite3.Connection | None = None
        try:
            while True:
                job = self._reads.get()
                if self._stopping:
                    return
                if self._unsettled():
                    self.flush(BUSY_TIMEOUT_S)  # a reader sees every event emitted before it asked
                error = None
                if conn is None:
                    try:
                        conn = connect(self.path)
                    except (sqlite3.Error, OSError) as exc:
                        error = f"cannot open {self.path}: {exc}"
                        # A full disk or a read-only mount: the history is still readable.
                        with contextlib.suppress(sqlite3.Error, OSError):
                            conn = connect_readonly(self.path)
                job(conn, error)
        finally:
            if conn is not None:
                conn.close()

    def diag(self) -> EventsDiag:
        return EventsDiag(
            written=self.written,
            queued=self.queued,
            dropped=self.dropped,
            lost=self.lost,
            failures=self.failures,
            last_error=self.last_error,
            file_bytes=self.file_bytes(),
        )


_Row = tuple[str, str, float, int | None]
"""A queued event: kind, details as JSON, wall time, scan cycle."""


def _row(details: KnownDetails, time: float, cycle: int | None) -> _Row:
    """An event as queued: plain text and numbers (see `EventLog.emit`)."""
    return (details.kind, dump_json(details), time, cycle)


_ReadJob = Callable[[sqlite3.Connection | None, str | None], None]
