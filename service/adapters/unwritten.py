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
  run's losses; a damaged line (a torn write, a power cut) costs that line alone, counted lost,
  and the file keeps them until they are in the database (a crash meanwhile loses nothing).
"""

from __future__ import annotations

import json
import logging
import os
from collections import deque
from collections.abc import Callable
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
        self._resumed: int | None = None
        """The previous run's events `resume` handed out and not yet seen written (None: the
        file holds nothing of its own to keep)."""

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
        """At the start: the previous run's unwritten events, its lost count and why (a damaged
        line costs itself, counted lost); the file reserved (written through) for this run's
        stop, and kept as it is until `committed` has seen the events written. Never raises."""
        try:
            text = self.path.read_text(encoding="utf-8", errors="replace")
        except FileNotFoundError:
            text = ""  # the first start here, or a log kept where nothing can be written
        except OSError as exc:
            log.warning("event=events_unwritten_unreadable path=%s error=%r", self.path, str(exc))
            self._write(b"")  # what it held cannot be had: reserve it for this run
            return [], 1, f"{self.path.name} unreadable ({exc.strerror or exc}); its events lost"
        lines = [line for line in text.splitlines() if line.strip()]
        if not lines:
            self._reserve()
            return [], 0, None
        rows, lost, error = _parse(lines, self.path)
        # Until these are in the database the file keeps them: a crash meanwhile (the disk
        # still full) writes them at the next start instead of losing them.
        self._resumed = len(rows)
        self._reserve()  # a file with content was reserved by the run that wrote it
        return rows, lost, error

    def committed(self, rows: int) -> None:
        """`rows` events from the queue (held ones first) are in the database: once the
        resumed ones must be among them, the file is blanked for this run's stop.

        A crash between that commit and the blanking writes them again at the next start: a
        duplicate E-stop record says what it is (the same time and details), a lost one says
        nothing."""
        if self._resumed is None:
            return
        self._resumed -= rows
        if self._resumed <= 0:
            self._resumed = None
            self._write(b"")

    def spill(self, lost: int, error: str | None) -> bool:
        """At the stop: what is held and the lost count into the reserved file (the oldest
        held events go first when it is too small: they are counted lost there)."""
        rows = self.take()
        if not rows and not lost:
            # What was resumed and not written yet is among `rows`: nothing left means the
            # file's record is in the database, or counted.
            return True if self._resumed is None else self._write(b"")
        lines = [_line(r) for r in rows]
        budget = RESERVE_BYTES - 512  # the head line
        while lines and sum(len(line) for line in lines) > budget:
            lines.pop(0)
            lost += 1
        head = json.dumps({"lost": lost, "error": error}).encode() + b"\n"
        self._resumed = None
        return self._write(head + b"".join(lines))

    def _write(self, data: bytes) -> bool:
        """`data`, padded with spaces to `RESERVE_BYTES`, over the file's own blocks."""
        return self._through(
            lambda fd: os.pwrite(fd, data.ljust(RESERVE_BYTES, b" ")[:RESERVE_BYTES], 0)
        )

    def _reserve(self) -> bool:
        """The file at `RESERVE_BYTES`, written: what it holds stays, spaces after it."""

        def pad(fd: int) -> None:
            size = os.fstat(fd).st_size
            if size < RESERVE_BYTES:
                os.pwrite(fd, b" " * (RESERVE_BYTES - size), size)

        return self._through(pad)

    def _through(self, write: Callable[[int], object]) -> bool:
        """`write` to the file (made if missing), then synced; False, and said, if it fails."""
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            log.warning("event=events_unwritten_failed path=%s error=%r", self.path, str(exc))
            return False
        try:
            write(fd)
            os.fsync(fd)
        except OSError as exc:
            log.warning("event=events_unwritten_failed path=%s error=%r", self.path, str(exc))
            return False
        finally:
            os.close(fd)
        return True


def _parse(lines: list[str], path: Path) -> tuple[list[Row], int, str | None]:
    """The file's lines (blank ones left out): every good row, the lost count, and why; a
    damaged line (a torn write, a power cut) costs itself, counted lost."""
    reasons: list[str] = []
    try:
        lost, error = _head(json.loads(lines[0]))
    except (ValueError, RecursionError) as exc:
        lost, error = 1, None
        reasons.append(f"the lost count in {path.name} unreadable ({str(exc)[:80]}): at least 1")
    if error:
        reasons.insert(0, error)
    rows: list[Row] = []
    damaged = 0
    for line in lines[1:]:
        try:
            rows.append(_row(json.loads(line)))
        except (ValueError, RecursionError):
            damaged += 1
    if damaged:
        lost += damaged
        reasons.append(f"{damaged} damaged line(s) in {path.name}, counted lost")
        log.warning("event=events_unwritten_damaged path=%s lines=%d", path, damaged)
    return rows, lost, "; ".join(reasons) or None


def _head(item: object) -> tuple[int, str | None]:
    """The head line's lost count and why; ValueError for anything that is not one."""
    if isinstance(item, dict):
        lost, error = item.get("lost", 0), item.get("error")
        if isinstance(lost, int) and lost >= 0 and (error is None or isinstance(error, str)):
            return lost, error
    raise ValueError(f"not the head line: {str(item)[:80]}")


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
