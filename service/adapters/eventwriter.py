"""The event log's writer: a batch into the database in one transaction, what could not be
written held (safety events) or counted (the rest) and recorded as `storage_failed` once writing
works, retention between batches, and the rows written handed to the listeners.

`EventLog` (service/adapters/eventlog.py) is the façade the daemon calls: it queues, and its
writer thread hands each batch to the `EventWriter` it owns. The history process's writer
(service/adapters/history_writer.py) drives one the same way; for it, this module and those it
imports load no pydantic (the rows it makes itself are plain JSON, eventdb.py).
"""

from __future__ import annotations

import logging
import os
import sqlite3
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from ride_machine.schema.event_kinds import EventKind

from .eventdb import (
    Row,
    StoredRow,
    claim_writer,
    connect,
    damaged,
    dropped_row,
    insert,
    open_log,
    storage_failed_row,
    stored,
)
from .retention import Limits, prune_and_vacuum
from .unwritten import Unwritten

if TYPE_CHECKING:  # the history process writes rows alone, and loads no pydantic
    from ride_machine.service.core.history.held import Held

log = logging.getLogger(__name__)

STOP_BUSY_TIMEOUT_S = 0.2
"""Once stopping, how long a write waits for a database another process holds: the stop has a
deadline (the daemon ends the history process at it), and what is not written by then goes
into the file the next start writes (service/adapters/unwritten.py), safety events first."""

COALESCE_S = 0.02
"""How long a writer thread gathers events after the first one before writing them in one batch
(the daemon's `EventLog`, the history process's writer)."""

Listener = Callable[[list[StoredRow]], None]
"""Called with each committed batch, as stored (eventread's `row_event` makes a row an `Event`,
`row_payload` its wire bytes)."""


class Settings(Limits, Protocol):
    """What the writer reads of `[events]`: retention's limits and how often it prunes."""

    @property
    def prune_every_s(self) -> float: ...


class Counts(Protocol):
    """Where the writer keeps its counts: the event log's own (its `diag` reads them)."""

    written: int
    lost: int
    failures: int
    last_error: str | None


def _no_pause() -> None:
    """Between two chunks of a batch's inserts in the daemon: nothing (the history's own
    process gives way to the daemon's threads, service/adapters/history_writer.py)."""


class EventWriter:
    """Writes the batches of one event log into its database; what it wrote and could not
    write is counted in the log's `Counts`."""

    def __init__(
        self,
        counts: Counts,
        path: Path,
        machine_id: str,
        settings: Settings,
        pace: Callable[[], None] | None,
    ) -> None:
        self.counts = counts
        self.path = path
        self.machine_id = machine_id
        self.settings = settings
        self.pace = pace or _no_pause
        """Called between two chunks of a batch's inserts."""
        self.conn: sqlite3.Connection | None = None
        self._fd: int | None = None
        """`claim_writer`'s lock, held while this writes the log."""
        self.listeners: list[Listener] = []
        self.failure: tuple[str, int] | None = None
        """The loss not yet recorded as `storage_failed`: its reason and its count."""
        self.dropped_recorded = 0
        """Of the log's dropped events, those recorded as `events_dropped`."""
        self.prune_due = 0.0
        self.unwritten = Unwritten(path)
        """The safety events a failed write left, kept across a stop (service/adapters/
        unwritten.py)."""

    # -------------------------------------------------------------------------- the file
    def claim(self, wait_s: float) -> None:
        """Wait for the log's previous writer to let go (`claim_writer`); said, not fatal."""
        self._fd, busy = claim_writer(self.path, wait_s)
        if busy is not None:
            log.error("event=events_writer_busy path=%s error=%r", self.path, busy)
            self.counts.last_error = busy

    def open_or_replace(self, now: float, bad: sqlite3.Error | None = None) -> bool | None:
        """Open the log (`open_log`): a file that is no event log is kept aside for a new one,
        which records that first; one that cannot open is said, its events counted as lost.
        Whether the last run in it ended with a `daemon_stop` (None: an empty log). `bad`: a
        write found the open log damaged, which is kept aside at once."""
        opened = open_log(self.path, now, bad)
        self.conn = opened.conn
        clean = None if opened.last_kind is None else opened.last_kind == EventKind.DAEMON_STOP
        if opened.aside is None:
            if opened.error is not None:
                self.fail(opened.error, 0)
            return clean
        error = (
            f"{self.path} was not a usable event log ({opened.error}); kept as {opened.aside.name}"
        )
        log.error(
            "event=events_db_set_aside path=%s aside=%s error=%r",
            self.path,
            opened.aside,
            opened.error,
        )
        self.counts.failures += 1
        self.counts.last_error = error
        self.failure = (error, self.failure[1] if self.failure is not None else 0)
        return clean

    def resume_unwritten(self) -> list[Row]:
        """What the previous run could not write: its safety events, to be queued first; its
        lost count goes with the first write as a `storage_failed` event."""
        rows, lost, error = self.unwritten.resume()
        if lost:
            why = f"in the previous run: {error or 'events not written'}"
            if self.failure is not None:
                why, lost = f"{self.failure[0]}; {why}", lost + self.failure[1]
            self.failure = (why, lost)
        return rows

    def release(self) -> None:
        """Close the database and let the next writer of this log start."""
        if self.conn is not None:
            self.conn.close()
            self.conn = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    # ------------------------------------------------------------------------- a batch
    def write(self, batch: list[Row], dropped_total: int, stopping: bool, now: float) -> None:
        """`batch`, after a `storage_failed` for an earlier loss (stamped `now`), an
        `events_dropped` for the drops not yet recorded (of `dropped_total`) and the safety
        events held."""
        items: list[Row] = []
        if self.failure is not None:
            items.append(storage_failed_row(*self.failure, now))
        dropped = dropped_total - self.dropped_recorded
        if dropped:
            items.append(dropped_row(dropped, now))
        held = self.unwritten.take()
        items += held + batch
        conn = self.conn
        if conn is None:
            conn = self._reopen()
        if conn is None:
            lost = self.unwritten.hold(held + batch)
            self.fail(self.counts.last_error or "event log unavailable", lost)
            return
        machine_id = self.machine_id
        try:
            if stopping:
                conn.execute(f"PRAGMA busy_timeout = {int(STOP_BUSY_TIMEOUT_S * 1000)}")
            last = insert(conn, machine_id, items, self.pace)
        except sqlite3.Error as exc:
            # The safety record waits in memory for the next write; the rest is lost.
            self.fail(str(exc), self.unwritten.hold(held + batch))
            if damaged(exc):  # it stays so: kept aside for a new log, as a start does
                conn.close()
                self.open_or_replace(now, exc)
            return
        self.failure = None
        self.dropped_recorded += dropped
        self.counts.written += len(items)
        self.unwritten.committed(len(held) + len(batch))  # the previous run's file, once written
        if self.listeners:
            self.publish(stored(last, machine_id, items))

    def owes(self, dropped_total: int) -> bool:
        """Something to write without a batch: drops to record, or safety events held (tried
        again every wait, at most 1 s)."""
        return dropped_total > self.dropped_recorded or bool(len(self.unwritten))

    def publish(self, rows: list[StoredRow]) -> None:
        """The rows just written, to every listener (on the writer's thread)."""
        for listener in self.listeners:
            try:
                listener(rows)
            except Exception as exc:  # noqa: BLE001 - a publishing failure loses no stored event
                log.warning("event=events_publish_failed error=%r", str(exc))

    def fail(self, error: str, lost: int, exc: BaseException | None = None) -> None:
        """`lost` events not written: counted, recorded as `storage_failed` once writing works,
        and logged once per problem (`exc`: with its traceback, a bug rather than a disk)."""
        counts = self.counts
        counts.failures += 1
        counts.lost += lost
        counts.last_error = error
        ongoing = self.failure is not None and self.failure[0] == error
        total = lost + (self.failure[1] if self.failure is not None else 0)
        self.failure = (error, total)
        # Once per problem, not once per batch: a full disk must not also fill the log.
        # Every loss is counted in diag and recorded as `storage_failed` once writing works.
        (log.debug if ongoing else log.error)(
            "event=events_write_failed error=%r lost=%d", error, lost, exc_info=exc
        )

    def _reopen(self) -> sqlite3.Connection | None:
        try:
            self.conn = connect(self.path)
        except (sqlite3.Error, OSError) as exc:
            self.counts.last_error = f"cannot open {self.path}: {exc}"
            return None
        return self.conn

    # ---------------------------------------------------------------- retention, the stop
    def prune(self, now: float, write_queued: Callable[[], None]) -> None:
        """Drop what retention says (service/adapters/retention.py): routine events by age and
        the file's size, the safety record by its own age and size."""
        self.prune_due = now + self.settings.prune_every_s
        if self.conn is None:
            return
        try:
            prune_and_vacuum(self.conn, self.settings, now, write_queued)
        except sqlite3.Error as exc:
            log.warning("event=events_prune_failed error=%r", str(exc))

    def spill(self, queued: Sequence[Row | Held], dropped_total: int) -> None:
        """At the stop: what is unwritten (held safety events, events lost or dropped and not
        yet recorded) into the file the next start reads (service/adapters/unwritten.py)."""
        rows = [item for item in queued if isinstance(item, tuple)]  # not a `Held`
        error, failed = self.failure or (None, 0)
        lost = dropped_total - self.dropped_recorded + len(queued) - len(rows) + failed
        lost += self.unwritten.hold(rows)
        self.unwritten.spill(lost, error or (f"{lost} events not written" if lost else None))
