"""The event history's SQLite file: its table and rows, a connection to it, one writer at a time,
a batch written in one transaction, and a file that is no event log set aside."""

from __future__ import annotations

import contextlib
import fcntl
import os
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from ride_machine.schema.event_kinds import EventKind
from ride_machine.service.core.history.facts import wire_json

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
INSERT_CHUNK = 16
"""Rows inserted per `executemany` of a batch (all in its one transaction), `pace` between."""

Row = tuple[str, str, float, int | None]
"""An event to write: kind, details as JSON, wall time, scan cycle. Plain text and numbers,
which the garbage collector never scans: a queue of them filled by a stalled disk does not
make the scan thread's collections longer."""
StoredRow = tuple[int, float, int | None, str, str, str]
"""An event as stored: seq, time, cycle, machine_id, kind, and its details as JSON text."""

CACHE_KIB = 512
"""SQLite's page cache per connection: a writer appends, and a page of a read is at most 500
rows (~25 pages of 4 KiB); SQLite's default (2 MiB) filled up and stayed in every process that
writes the history (bench.rss_soak)."""

BUSY_TIMEOUT_S = 1.0
"""How long a write or read waits for a database another process holds locked before it
counts as failed: short, so a locked file can never hold up start-up or the shutdown deadline."""


WRITER_WAIT_S = 5.0
"""How long a log's writer waits at start for the one before it to let go (`claim_writer`):
the history process of a killed daemon still writes what it was sent, for milliseconds."""
WRITER_POLL_S = 0.01


class ForeignDatabase(sqlite3.DatabaseError):
    """A SQLite file whose `events` table is not ours (another program's, or an old layout)."""


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
        conn.execute(f"PRAGMA cache_size = -{CACHE_KIB}")
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


def damaged(exc: BaseException) -> bool:
    """Whether a write's `exc` says the file itself went bad while it was open (SQLite's
    CORRUPT, NOTADB): `unusable`, less what a bad row raises (a constraint, a wrong value)."""
    code = (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF  # an extended code's primary
    return unusable(exc) and code in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)


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


class Opened(NamedTuple):
    """What `open_log` found: a connection (None: none could be made, `error` says why) and
    the newest event's kind; `aside`, where a file that was no event log went (`error`: why).
    A tuple, not a dataclass: the history process loads no `dataclasses` (and its `inspect`,
    1.3 MiB resident)."""

    conn: sqlite3.Connection | None
    last_kind: str | None = None
    error: str | None = None
    aside: Path | None = None


def open_log(path: Path, now: float, bad: BaseException | None = None) -> Opened:
    """The log at `path` opened for writing; a file that is no event log (`unusable`) is set
    aside and a new log made in its place. `bad`: what a write found wrong with the file
    (`damaged`), which sets it aside without a try."""
    if bad is None:
        try:
            return _open(path)
        except (sqlite3.Error, OSError) as exc:
            if not unusable(exc):
                return Opened(None, error=f"cannot open {path}: {exc}")
            bad = exc
    try:
        aside = set_aside(path, now)
        opened = _open(path)
    except (sqlite3.Error, OSError) as again:
        return Opened(None, error=f"cannot open {path}: {bad}; cannot replace it: {again}")
    return Opened(opened.conn, opened.last_kind, str(bad), aside)


def _open(path: Path) -> Opened:
    conn = connect(path)
    try:
        # fetchall: a cursor left open would hold a read transaction for good.
        rows = conn.execute("SELECT kind FROM events ORDER BY seq DESC LIMIT 1").fetchall()
    except BaseException:
        conn.close()
        raise
    return Opened(conn, rows[0][0] if rows else None)


def connect_readonly(path: Path) -> sqlite3.Connection:
    """Read an existing log (the offline export); never creates or changes the file."""
    if not path.is_file():
        raise FileNotFoundError(f"no event log at {path}")
    return sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0, check_same_thread=False)


def file_bytes(path: Path) -> int:
    """The database file and its WAL on disk."""
    total = 0
    for suffix in ("", "-wal"):
        with contextlib.suppress(OSError):  # not there (yet): counts as empty
            total += os.path.getsize(f"{path}{suffix}")
    return total


def insert(
    conn: sqlite3.Connection, machine_id: str, rows: list[Row], pace: Callable[[], None]
) -> int:
    """Write `rows` in one transaction, `pace()` between chunks; the seq of the last (the
    others are the ones before it). Rolled back, and raised, when the write fails."""
    try:
        conn.execute("BEGIN")
        for at in range(0, len(rows), INSERT_CHUNK):
            chunk = rows[at : at + INSERT_CHUNK]
            conn.executemany(_INSERT, [(w, c, machine_id, k, d) for k, d, w, c in chunk])
            pace()
        # One transaction holds the write lock: AUTOINCREMENT numbered the batch in a row.
        [(last,)] = conn.execute("SELECT last_insert_rowid()").fetchall()
        conn.execute("COMMIT")
    except sqlite3.Error:
        if conn.in_transaction:
            with contextlib.suppress(sqlite3.Error):  # the disk that failed the write
                conn.execute("ROLLBACK")
        raise
    return int(last)


def stored(last: int, machine_id: str, rows: list[Row]) -> list[StoredRow]:
    """`rows` as `insert` stored them, the last one numbered `last`."""
    first = last - len(rows) + 1
    return [
        (first + i, when, cycle, machine_id, kind, details)
        for i, (kind, details, when, cycle) in enumerate(rows)
    ]


def storage_failed_row(error: str, lost: int, wall: float) -> Row:
    """A `storage_failed` event of the event log (a `StorageEvent` of `what="events"`) as it is
    written, made without the model (the history process loads no pydantic)."""
    kind = EventKind.STORAGE_FAILED._value_
    text = wire_json({"kind": kind, "what": "events", "error": error, "lost": lost})
    return (kind, text, wall, None)


def dropped_row(count: int, wall: float) -> Row:
    """An `events_dropped` event (a `DroppedEvent`) as it is written, made without the model."""
    kind = EventKind.EVENTS_DROPPED._value_
    return (kind, wire_json({"kind": kind, "count": count}), wall, None)
