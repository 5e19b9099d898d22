"""A queue of events and the thread that writes it through an `EventWriter`: what the daemon's
`EventLog` (service/adapters/eventlog.py) and the history process's writer
(service/adapters/history_writer.py) share.

A batch per wake-up, gathered for `COALESCE_S` unless hurried; retention between batches; a
stop that writes what is queued while it can and leaves the rest to `close`'s spill. What an
item of the queue is, and how a batch is made of them, is each one's own (`_take`). It loads no
pydantic: the history process runs it.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Generic, Protocol, TypeVar

from ride_machine.service.threads import NamedThread

from .eventdb import Row
from .eventwriter import COALESCE_S, EventWriter
from .retention import SAFETY_KINDS

SAFETY_RESERVE = 256
"""Room past a queue's capacity for the safety record's events only (an E-stop, a fault, a
watchdog trip): a queue that routine events filled (a flood of commands while the disk or the
history process stalls) still takes them. Each comes from a change of the machine, not from a
stream, so this is more than a stall of the history (10 s, history_ledger.STALL_S) sees."""


class QueueSettings(Protocol):
    """What the thread reads of `[events]`."""

    @property
    def batch_max(self) -> int: ...

    @property
    def prune_every_s(self) -> float: ...


S = TypeVar("S", bound=QueueSettings)


class WriterThread(Generic[S]):
    """The queue (`_items`, under `_lock`), the writer thread (`_run`) and the counts the
    `EventWriter` keeps in it (`written`, `lost`, `failures`, `last_error`, `dropped`)."""

    writer: EventWriter
    settings: S
    wall: Callable[[], float]

    def __init__(self) -> None:
        self._items: deque[Any] = deque()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._hurry = threading.Event()
        """Set by a reader or `flush`: write what is queued now, without gathering more."""
        self._stopping = False
        self._busy = False
        """A batch taken and not yet written (or drops not yet recorded)."""
        self._thread: threading.Thread | None = None
        """The writer thread (`_run`)."""
        self.dropped = 0
        self.written = 0
        self.lost = 0
        self.failures = 0
        self.last_error: str | None = None

    # ------------------------------------------------------------------------ lifecycle
    def _start_writing(self) -> None:
        self._thread = NamedThread(target=self._run, name="eventlog", daemon=True)
        self._thread.start()

    def _stop_taking(self) -> None:
        """No more events taken; the writer hurried to the end of the queue."""
        with self._lock:
            self._stopping = True
        self._wake.set()
        self._hurry.set()

    def _join(self, deadline: float) -> bool:
        """Wait for the writer thread to end (at most until `deadline`); False while it is
        still writing (a thread waiting on a locked file is left behind: a daemon thread)."""
        if self._thread is not None:
            self._thread.join(max(0.0, deadline - time.monotonic()))
        return self._thread is None or not self._thread.is_alive()

    def _spill(self, queued: list[Any]) -> None:
        """What the stop could not write, into the file the next start writes first."""
        self.writer.spill(queued, self.dropped)
        self.writer.release()  # the next writer of this log may start

    def _take_all(self) -> list[Any]:
        with self._lock:
            queued = list(self._items)
            self._items.clear()
        return queued

    # --------------------------------------------------------------------------- queue
    def _admit(self, items: Sequence[Any], capacity: int) -> None:
        """Queue `items` in order (rows, and whatever else the queue holds), each while there
        is room: `capacity`, or `SAFETY_RESERVE` past it for an event of the safety record;
        events left out are dropped and counted, anything else (a log line) just left out."""
        with self._lock:
            queue = self._items
            for item in items:
                row = isinstance(item, tuple)
                limit = capacity + SAFETY_RESERVE if row and item[0] in SAFETY_KINDS else capacity
                if len(queue) < limit and not self._stopping:
                    queue.append(item)
                elif row:
                    self.dropped += 1
        self._wake_writer()

    def _wake_writer(self) -> None:
        if not self._wake.is_set():  # set() takes a Condition's lock: once per batch is enough
            self._wake.set()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until everything queued so far is written (at most `timeout`)."""
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

    def _pop_batch(self) -> list[Any]:
        """Under the lock: up to `batch_max` items off the queue (`_taken` sees them there)."""
        with self._lock:
            n = min(len(self._items), self.settings.batch_max)
            batch = [self._items.popleft() for _ in range(n)]
            self._busy = bool(batch) or self.dropped > self.writer.dropped_recorded
            if not self._items:
                self._wake.clear()
            self._taken(batch)
        return batch

    def _taken(self, batch: list[Any]) -> None:
        """Under the lock, the batch just taken off the queue (nothing by default)."""

    def _take(self) -> list[Row]:
        """The next batch as rows."""
        rows: list[Row] = self._pop_batch()
        return rows

    # ---------------------------------------------------------------------------- thread
    def _gather(self, timeout: float) -> None:
        """Wait for the next event (at most `timeout`), then gather what follows for a moment
        (unless hurried): a write (and its publications) per event took the GIL from the Zenoh
        thread replying to the next command."""
        if self._wake.wait(timeout):
            self._hurry.wait(COALESCE_S)
        self._hurry.clear()

    def _run(self) -> None:
        writer = self.writer
        while True:
            self._gather(min(1.0, self.settings.prune_every_s))
            batch: list[Row] = []
            failures = self.failures
            try:
                batch = self._take()
                if batch or writer.owes(self.dropped):
                    self._write(batch)
            except Exception as exc:  # noqa: BLE001 - one bad batch must not end the history
                writer.fail(f"event writer failed: {exc!r}", len(batch), exc)
            finally:
                self._busy = False
            gave_up = self._stopping and self.failures > failures
            if self.wall() >= writer.prune_due and not self._stopping:
                try:
                    self._prune()
                except Exception as exc:  # noqa: BLE001 - nor one bad prune
                    writer.fail(f"event prune failed: {exc!r}", 0, exc)
            with self._lock:
                # A write that failed in the stop (a locked or full disk) is not tried again:
                # waiting on it would pass the stop's deadline, and the process killed there
                # spills nothing; `close` puts the rest, safety events kept, in the file.
                if self._stopping and (not self._items or gave_up):
                    return

    def _write(self, batch: list[Row]) -> None:
        """One batch to the writer, with the drops it has yet to record."""
        self.writer.write(batch, self.dropped, self._stopping, self.wall())

    def _prune(self) -> None:
        """Retention (`EventWriter.prune`), writing first what comes in while it runs."""
        self.writer.prune(self.wall(), self._write_queued)

    def _write_queued(self) -> None:
        """Between retention's chunks: what came in meanwhile."""
        batch = self._take()
        if batch:
            self._write(batch)
