"""Reading the event history: stored rows as events or as their wire bytes, bounded pages for
queries, every event for the export, and the thread that answers queries off the scan thread."""

from __future__ import annotations

import contextlib
import json
import queue
import sqlite3
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ride_machine.schema.codec import pack
from ride_machine.schema.events import Event, EventPage, EventQuery
from ride_machine.service.threads import NamedThread

from .eventdb import StoredRow, connect, connect_readonly

MAX_PAGE_BYTES = 256 * 1024
"""A reply page stops growing past this many bytes of event JSON (and says `more`)."""


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


ReadJob = Callable[[sqlite3.Connection | None, str | None], None]
"""A query to answer with the reader's connection (None, and why, when there is none)."""


class Reader:
    """The thread that answers queries on a connection of its own (WAL: it reads while the
    writer writes); `catch_up` first writes what was emitted before the query came."""

    def __init__(
        self,
        path: Path,
        machine_id: str,
        page_max: int,
        *,
        stopping: Callable[[], bool],
        catch_up: Callable[[], None],
    ) -> None:
        self.path = path
        self.machine_id = machine_id
        self.page_max = page_max
        self._stopping = stopping
        self._catch_up = catch_up
        self._jobs: queue.Queue[ReadJob] = queue.Queue(maxsize=32)
        self._thread = NamedThread(target=self._serve, name="eventlog-read", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Wake the thread to see that the log stops (it ends there)."""
        with contextlib.suppress(queue.Full):
            self._jobs.put_nowait(lambda conn, error: None)

    def join(self, timeout: float) -> None:
        if self._thread.ident is not None:  # started
            self._thread.join(timeout)

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
                page = read_page(conn, self.machine_id, q, self.page_max)
            except Exception as exc:  # noqa: BLE001 - the reader thread must answer the next query too
                fail(f"event log read failed: {exc}")
                return
            respond(page)

        try:
            self._jobs.put_nowait(job)
        except queue.Full:
            return False
        return True

    def _serve(self) -> None:
        conn: sqlite3.Connection | None = None
        try:
            while True:
                job = self._jobs.get()
                if self._stopping():
                    return
                self._catch_up()  # a reader sees every event emitted before it asked
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
