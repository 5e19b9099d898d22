"""The event history's retention: routine events by `[events] max_age_days` and `max_mb`, the
safety record by its own `safety_max_age_days` and `safety_max_mb`.

About 260 000 `check/home` commands (25 s at the measured rate) pushed a 64 MB history past its
limit, and the next prune, oldest first, took an E-stop from two minutes before with them. Now a
flood of routine events (commands, states, completions, sessions) only ever pushes out routine
events; the safety record is pruned for its own age and size alone, and there, the events a bus
login can cause at will (faults of refused sessions, Riders lost, safety-setting writes) go
before the ones it cannot (E-stops, watchdog trips, the daemon's starts and stops).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from typing import Protocol

from ride_machine.schema.event_kinds import EventKind


class Limits(Protocol):
    """What retention reads of `[events]` (`EventsSection`, or the history process's own plain
    copy of it, service/adapters/history_writer.py: no pydantic there)."""

    @property
    def max_age_days(self) -> float: ...

    @property
    def max_mb(self) -> float: ...

    @property
    def safety_max_age_days(self) -> float: ...

    @property
    def safety_max_mb(self) -> float: ...


_K = EventKind
PROTECTED = (
    _K.ESTOP_PRESSED,
    _K.ESTOP_RELEASED,
    _K.ESTOP_LATCHED,
    _K.ESTOP_RESET,
    _K.WATCHDOG_TRIP,
    _K.DAEMON_START,
    _K.DAEMON_STOP,
    _K.STORAGE_FAILED,
)
"""The safety record no login on the bus can add to at will: pruned last."""
CAUSABLE = (
    _K.FAULT_RAISED,
    _K.FAULT_CLEARED,
    _K.RIDER_LOST,
    _K.RIDER_RETURNED,
    _K.SAFETY_CHANGED,
    _K.CALIBRATION,
    _K.PARAM_CHANGED,
    _K.EVENTS_DROPPED,
)
"""The safety record a `rider` login can add to (an invalid session faults; a Rider that
connects and leaves; a safety setting, a calibration or a parameter written): pruned first,
within its own limit. Who entered which gain two minutes before a ride went wrong must not go
with a flood of cheap commands (issue 58, point 5)."""
SAFETY_KINDS = frozenset(k.value for k in (*PROTECTED, *CAUSABLE))

PRUNE_CHUNK = 2000
"""Rows deleted per transaction, so queued events are written in between."""
ROW_OVERHEAD = 48
"""Bytes a row costs besides its details text (its other columns, the two indexes): for the
safety record's size, which SQLite cannot tell apart from the rest of the file."""


def _in(kinds: tuple[str, ...] | frozenset[str]) -> str:
    return ",".join(f"'{k}'" for k in sorted(kinds))


_SAFETY = _in(SAFETY_KINDS)


def prune(
    conn: sqlite3.Connection, settings: Limits, now: float, between: Callable[[], None]
) -> None:
    """Drop what retention says, a chunk at a time (`between` writes what was queued meanwhile)."""
    routine = f"kind NOT IN ({_SAFETY})"
    safety_cutoff = now - settings.safety_max_age_days * 86_400
    for where, args in (
        (f"{routine} AND time < ?", (now - settings.max_age_days * 86_400,)),
        (f"kind IN ({_SAFETY}) AND time < ?", (safety_cutoff,)),
    ):
        while _delete(conn, where, args, PRUNE_CHUNK) == PRUNE_CHUNK:
            between()
    safety_limit = int(settings.safety_max_mb * 1024 * 1024)
    safety = safety_bytes(conn)
    for tier in (CAUSABLE, PROTECTED):
        where = f"kind IN ({_in(tier)})"
        per_row = _per_row(conn, where) if safety > safety_limit else 0.0
        while safety > safety_limit and per_row:
            gone = _delete(conn, where, (), _rows(safety - safety_limit, per_row))
            if gone == 0:
                break
            safety -= int(gone * per_row)
            between()
    limit = int(settings.max_mb * 1024 * 1024)
    per_row = 0.0
    while (used := used_bytes(conn)) > limit:
        # The average routine row, measured once (a scan of the whole table), not per chunk.
        per_row = per_row or _per_row(conn, routine)
        # Down to 90 % of the limit, by the average row size: never all at once.
        if not per_row or _delete(conn, routine, (), _rows(used - 0.9 * limit, per_row)) == 0:
            break  # only the safety record is left: it keeps to its own limit
        between()


def prune_and_vacuum(
    conn: sqlite3.Connection, settings: Limits, now: float, between: Callable[[], None]
) -> None:
    """`prune`, then the freed pages given back to the file system and the WAL truncated."""
    prune(conn, settings, now, between)
    conn.execute("PRAGMA incremental_vacuum")
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")


def used_bytes(conn: sqlite3.Connection) -> int:
    """Bytes of the database in use (free pages not counted)."""
    page = conn.execute("PRAGMA page_size").fetchone()[0]
    count = conn.execute("PRAGMA page_count").fetchone()[0]
    free = conn.execute("PRAGMA freelist_count").fetchone()[0]
    return int(page * (count - free))


def safety_bytes(conn: sqlite3.Connection) -> int:
    """About what the safety record takes in the file (its details, and a row's overhead)."""
    text, rows = _size(conn, f"kind IN ({_SAFETY})")
    return text + ROW_OVERHEAD * rows


def _size(conn: sqlite3.Connection, where: str) -> tuple[int, int]:
    """The details' bytes and the number of the rows that match `where`."""
    sql = f"SELECT COALESCE(SUM(LENGTH(details)), 0), COUNT(*) FROM events WHERE {where}"
    [(text, rows)] = conn.execute(sql).fetchall()
    return int(text), int(rows)


def _per_row(conn: sqlite3.Connection, where: str) -> float:
    """The average bytes of a row that matches `where` (0 when none does)."""
    text, rows = _size(conn, where)
    return (text + ROW_OVERHEAD * rows) / rows if rows else 0.0


def _rows(excess: float, per_row: float) -> int:
    """How many rows of `per_row` bytes make up about `excess` bytes (one chunk at most)."""
    return max(1, min(PRUNE_CHUNK, int(excess / max(1.0, per_row)) + 1))


def _delete(conn: sqlite3.Connection, where: str, args: tuple[object, ...], n: int) -> int:
    """The oldest `n` rows that match `where`; how many went."""
    if n <= 0:
        return 0
    cur = conn.execute(
        f"DELETE FROM events WHERE seq IN (SELECT seq FROM events WHERE {where} ORDER BY seq"
        " LIMIT ?)",
        (*args, n),
    )
    return cur.rowcount
