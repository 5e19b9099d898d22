"""What the daemon has given its history process and what the process has said of it: events sent
and settled, the safety record among them until the process confirms it, and when it last made
progress. Plain logic, the time an argument: service/adapters/history.py keeps one per process,
under its lock.

A process that confirms nothing for `STALL_S` while events wait for it has stalled (stopped, or
a disk that hangs under it): the daemon kills it, and the safety events it had not confirmed go
to the next process (or `close`'s spill) instead of being counted lost with the rest.
"""

from __future__ import annotations

from collections import deque

from .history_pipe import LINE, MADE, Item
from .retention import SAFETY_KINDS

STALL_S = 10.0
"""A process that confirms nothing for this long while events wait for it has stalled. Longer
than anything it does without a word back: a write waits 1 s for a locked database and then
says it failed; a prune's scans of a 64 MB file on an SD card take seconds."""
STARTUP_S = 30.0
"""A new process is waited for this long before its first word (its interpreter and imports on
a loaded host; the log's previous writer, waited for `WRITER_WAIT_S`)."""


def is_event(item: Item) -> bool:
    """An event (a log line is none)."""
    return bool(item[0] != LINE)


def is_safety(item: Item) -> bool:
    """An event of the safety record (a command's event is routine)."""
    return bool(item[0] == MADE and item[1] in SAFETY_KINDS)


def safety(items: list[Item]) -> list[Item]:
    """The safety record's events among `items`."""
    return [item for item in items if is_safety(item)]


def events_in(items: list[Item]) -> int:
    """The events among `items`."""
    return sum(is_event(item) for item in items)


def stalled_words() -> str:
    """Why a stalled process was killed, for `last_error` and its `storage_failed` record."""
    return f"it confirmed nothing for {STALL_S:g} s (stopped, or its disk hung)"


class Ledger:
    """One process's account: `sent` events, `settled` of them (written, dropped or counted
    lost there: its latest word), the safety events not yet settled, its last progress."""

    def __init__(self, now: float) -> None:
        self.sent = 0
        self.settled = 0
        self._unconfirmed: deque[tuple[int, Item]] = deque()
        """Each safety event sent and not settled, after the count of events it is (bounded by
        the pipe and the process's queue: it settles what it drops)."""
        self._progress_at = now + STARTUP_S
        """When it last settled events, or was given some while it had none."""

    def giving(self, now: float) -> None:
        """A batch is on its way: a process that had nothing to do is timed from now."""
        if self.sent == self.settled:
            self._progress_at = max(self._progress_at, now)

    def took(self, items: list[Item]) -> None:
        """The process took `items` whole."""
        counted = self.sent
        for item in items:
            if is_event(item):
                counted += 1
                if is_safety(item):
                    self._unconfirmed.append((counted, item))
        self.sent = counted

    def said(self, settled: int, now: float) -> None:
        """Its word: `settled` events; its first word ends the wait for its start."""
        if settled > self.settled or self._progress_at > now:
            self._progress_at = now
        self.settled = settled
        while self._unconfirmed and self._unconfirmed[0][0] <= settled:
            self._unconfirmed.popleft()

    def stalled(self, now: float, *, sending: bool) -> bool:
        """No progress for `STALL_S` while events sent (or being sent) wait."""
        return (sending or self.sent > self.settled) and now - self._progress_at > STALL_S

    def unconfirmed(self) -> tuple[int, list[Item]]:
        """At its end: how many routine events it had not settled (lost), and the safety
        events, for the next process; the ledger then owes nothing."""
        resend = [item for _, item in self._unconfirmed]
        lost = self.sent - self.settled - len(resend)
        self._unconfirmed.clear()
        self.sent = self.settled
        return lost, resend
