"""What the event log could not write yet: the safety record held in memory until the database
takes it, and, at the stop, kept in a file reserved at the start, with the count of the events
lost, for the next start to write.

A locked database (another process holding it, a backup tool) failed each batch, and an E-stop
in it was lost for good (counted as lost); a full disk lost the count too: the `storage_failed`
record that says how many went could never be written, and a restart forgot it. Now:

- a batch that cannot be written keeps its safety events (service/adapters/retention.py,
  `SAFETY_KINDS`) in memory, at most `HELD_MAX`, and the next write puts them first; routine
  events are counted lost, as before;
- at the stop, what is still held and the lost count go into `<events.db>.unwritten`, a file of
  `RESERVE_BYTES` written (not only sized) when the log starts: writing over its own blocks
  needs no free space, so this works on a disk that filled meanwhile (not on a read-only one);
- the next start writes them first, with a `storage_failed` event that counts the previous
  run's losses.
"""

from __future__ import annotations

import json
import logging
import os
from collections import deque
from pathlib import Path

from .eventdb import Row
from .retention import SAFETY_KINDS

log = logging.getLogger(__name__)

HELD_MAX = 10_000
"""Safety events held in memory at most while the database refuses them (about 3 MB)."""
RESERVE_BYTES = 256 * 1024
"""The file that takes the unwritten at the stop: a few hundred safety events."""


class Unwritten:
    """The safety events a failed write left, and the file that keeps them across a stop."""

    def __init__(self, db: Path) -> None:
        self.path = db.with_name(db.name + ".unwritten")
        self._held: deque[Row] = deque()

    def __len__(self) -> int:
        return len(self._held)

    # ------------------------------------------------------------------------ in memory
    def hold(self, rows: list[Row]) -> int:
        """Keep the safety events of a batch that was not written; how many are lost: the
        routine ones, and held ones pushed out by newer ones beyond `HELD_MAX`."""
        kept = [r for r in rows if r[0] in SAFETY_KINDS]
        self._held.extend(kept)
        pushed = max(0, len(self._held) - HELD_MAX)
        for _ in range(pushed):
            self._held.popleft()
        return len(rows) - len(kept) + pushed

    def take(self) -> list[Row]:
        """What is held, for the next write (held again if that one fails too)."""
        rows = list(self._held)
        self._held.clear()
        return rows

    # ------------------------------------------------------------------------- the file
    def resume(self) -> tuple[list[Row], int, str | None]:
        """At the start: the previous run's unwritten events, its lost count and why; the file
        then reserved (written through) for this run's stop. Never raises."""
        rows: list[Row] = []
        lost, error = 0, None
        try:
            text = self.path.read_text(encoding="utf-8", errors="replace")
            lines = [line for line in text.splitlines() if line.strip()]
            if lines:
                head = json.loads(lines[0])
                lost, error = int(head.get("lost", 0)), head.get("error")
                rows = [_row(json.loads(line)) for line in lines[1:]]
        except FileNotFoundError:
            pass  # the first start here, or a log kept where nothing can be written
        except (OSError, ValueError, TypeError, AttributeError) as exc:
            log.warning("event=events_unwritten_unreadable path=%s error=%r", self.path, str(exc))
        self._write(b"")  # reserve (and clear) it for this run
        return rows, lost, error

    def spill(self, lost: int, error: str | None) -> bool:
        """At the stop: what is held and the lost count into the reserved file (the oldest
        held events go first when it is too small: they are counted lost there)."""
        rows = self.take()
        if not rows and not lost:
            return True
        lines = [_line(r) for r in rows]
        budget = RESERVE_BYTES - 512  # the head line
        while lines and sum(len(line) for line in lines) > budget:
            lines.pop(0)
            lost += 1
        head = json.dumps({"lost": lost, "error": error}).encode() + b"\n"
        return self._write(head + b"".join(lines))

    def _write(self, data: bytes) -> bool:
        """`data`, padded with spaces to `RESERVE_BYTES`, over the file's own blocks."""
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            log.warning("event=events_unwritten_failed path=%s error=%r", self.path, str(exc))
            return False
        try:
            os.pwrite(fd, data.ljust(RESERVE_BYTES, b" ")[:RESERVE_BYTES], 0)
            os.fsync(fd)
        except OSError as exc:
            log.warning("event=events_unwritten_failed path=%s error=%r", self.path, str(exc))
            return False
        finally:
            os.close(fd)
        return True


def _line(row: Row) -> bytes:
    return json.dumps(list(row), separators=(",", ":")).encode() + b"\n"


def _row(item: object) -> Row:
    """A row read back from the file; ValueError for anything that is not one."""
    if isinstance(item, list) and len(item) == 4:
        kind, details, when, cycle = item
        if (
            isinstance(kind, str)
            and isinstance(details, str)
            and isinstance(when, int | float)
            and (cycle is None or isinstance(cycle, int))
        ):
            return kind, details, float(when), cycle
    raise ValueError(f"not an event row: {str(item)[:80]}")
