"""The file that carries a stop's unwritten safety events to the next start
(service/adapters/unwritten.py): a damaged line costs that line alone, counted, and the file
keeps its events until the database has them."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest

from ride_machine.schema.events import EstopEvent, FaultEvent
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.eventdb import Row, connect
from ride_machine.service.adapters.eventlog import EVENTS_FILE, as_row
from ride_machine.service.adapters.eventwriter import EventWriter
from ride_machine.service.adapters.unwritten import RESERVE_BYTES, Unwritten
from tests.service.adapters.eventlog_support import T0

ESTOP = as_row(EstopEvent(kind="estop_pressed", state=MachineState.RUNNING), T0, 1)
FAULT = as_row(FaultEvent(kind="fault_raised", code="TILT_TIMEOUT", message="stuck"), T0 + 1, 2)


def head(lost: int, error: str | None) -> bytes:
    return json.dumps({"lost": lost, "error": error}).encode() + b"\n"


def line(row: Row) -> bytes:
    return json.dumps(list(row), separators=(",", ":")).encode() + b"\n"


def left_by_a_stop(db: Path, *lines: bytes) -> Path:
    """The file a previous run's stop wrote (the reserved size, spaces after the lines)."""
    path = db.with_name(db.name + ".unwritten")
    path.write_bytes(b"".join(lines).ljust(RESERVE_BYTES, b" "))
    return path


@pytest.mark.hazard("H41")
def test_a_torn_line_costs_that_line_and_keeps_the_rows_before_it(tmp_path: Path) -> None:
    db = tmp_path / EVENTS_FILE
    left_by_a_stop(db, head(2, "database is locked"), line(ESTOP), line(FAULT)[:30])
    rows, lost, error = Unwritten(db).resume()
    assert rows == [ESTOP]
    assert lost == 2 + 1
    assert error is not None and "database is locked" in error
    assert "1 damaged line(s)" in error


def test_an_unreadable_head_line_keeps_the_rows_and_counts_one_lost(tmp_path: Path) -> None:
    db = tmp_path / EVENTS_FILE
    left_by_a_stop(db, b'{"lost": 4, "err\n', line(ESTOP), line(FAULT))
    rows, lost, error = Unwritten(db).resume()
    assert rows == [ESTOP, FAULT]
    assert lost == 1  # at least one: how many is unknown
    assert error is not None and "lost count" in error and "unreadable" in error


def test_a_first_start_reserves_the_file_for_its_stop(tmp_path: Path) -> None:
    db = tmp_path / EVENTS_FILE
    assert Unwritten(db).resume() == ([], 0, None)
    path = db.with_name(db.name + ".unwritten")
    assert path.stat().st_size == RESERVE_BYTES and path.read_bytes().strip() == b""


@pytest.mark.hazard("H41")
def test_a_resumed_file_stays_until_its_events_are_in_the_database(
    writer: EventWriter,
) -> None:
    """Cleared at the start, the file lost the E-stop to a crash while the disk was still full;
    it is now blanked only once a write has committed what it held."""
    content = head(1, "disk full") + line(ESTOP)
    path = left_by_a_stop(writer.path, content)
    rows = writer.resume_unwritten()
    assert rows == [ESTOP]
    assert path.stat().st_size == RESERVE_BYTES  # still reserved for this run's stop

    blocker = sqlite3.connect(writer.path, timeout=0.1, isolation_level=None)
    try:
        blocker.execute("BEGIN EXCLUSIVE")  # another process holds the log
        assert writer.conn is not None
        writer.conn.execute("PRAGMA busy_timeout=10")
        writer.write(rows, 0, False, T0 + 2)
        assert writer.counts.failures == 1
        assert path.read_bytes().rstrip(b" ") == content  # a crash now loses nothing
        blocker.execute("ROLLBACK")
    finally:
        blocker.close()

    writer.write([], 0, False, T0 + 3)  # the held E-stop goes first
    assert writer.counts.failures == 1
    assert path.stat().st_size == RESERVE_BYTES and path.read_bytes().strip() == b""
    with connect(writer.path) as conn:
        kinds = [k for (k,) in conn.execute("SELECT kind FROM events ORDER BY seq")]
    assert kinds[-2:] == ["storage_failed", "estop_pressed"]
