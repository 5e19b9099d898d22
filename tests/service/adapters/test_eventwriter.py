"""The event log's writer (service/adapters/eventwriter.py), one write at a time: a log that
goes bad while it runs is kept aside and a new one begun, as a start does."""

from __future__ import annotations

import json
from contextlib import closing
from pathlib import Path

import pytest

from ride_machine.service.adapters.eventdb import connect
from ride_machine.service.adapters.eventlog import EVENTS_FILE, as_row
from ride_machine.service.adapters.eventwriter import EventWriter
from tests.service.adapters.eventlog_support import T0, note
from tests.service.adapters.test_unwritten import ESTOP


def _spoil_under(writer: EventWriter) -> bytes:
    """The open log's header overwritten once its pages are in the file: checkpointed by
    another connection (a reader's), so the writer's next transaction reads the file again and
    finds no database. The bytes written."""
    with closing(connect(writer.path)) as other:
        other.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    garbage = b"\xa5" * 100
    with writer.path.open("r+b") as f:
        f.write(garbage)
    return garbage


@pytest.mark.hazard("H40")
def test_a_log_damaged_while_running_is_kept_aside_and_the_next_batch_written(
    writer: EventWriter, tmp_path: Path
) -> None:
    writer.write([as_row(note(1.0), T0, 1)], 0, False, T0)
    garbage = _spoil_under(writer)
    writer.write([ESTOP, as_row(note(2.0), T0 + 1, 2)], 0, False, T0 + 1)  # fails: no database
    [aside] = tmp_path.glob(f"{EVENTS_FILE}.bad-*")
    assert aside.read_bytes().startswith(garbage)  # kept as it was found
    writer.write([as_row(note(3.0), T0 + 2, 3)], 0, False, T0 + 2)
    with closing(connect(writer.path)) as conn:
        rows = conn.execute("SELECT kind, details FROM events ORDER BY seq").fetchall()
    assert [kind for kind, _ in rows] == ["storage_failed", "estop_pressed", "session_ended"]
    failed = json.loads(rows[0][1])
    assert aside.name in failed["error"] and "not a usable event log" in failed["error"]
    assert failed["lost"] == 1  # the failed batch's routine event; its E-stop was held
    assert writer.counts.lost == 1
    assert json.loads(rows[2][1])["duration_s"] == 3.0


def test_a_bad_row_is_no_reason_to_set_the_log_aside(writer: EventWriter, tmp_path: Path) -> None:
    writer.write([("note", None, T0, 1)], 0, False, T0)  # type: ignore[list-item]
    writer.write([as_row(note(1.0), T0 + 1, 2)], 0, False, T0 + 1)
    assert list(tmp_path.glob(f"{EVENTS_FILE}.bad-*")) == []
    with closing(connect(writer.path)) as conn:
        kinds = [k for (k,) in conn.execute("SELECT kind FROM events ORDER BY seq").fetchall()]
    assert kinds == ["storage_failed", "session_ended"]
