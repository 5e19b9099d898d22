"""`machine events export`: CSV and JSON lines from the database file, offline."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import time
from pathlib import Path

import pytest

from ride_machine.schema.events import CommandEvent, DaemonStopEvent, Event, parse_point
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.export import CSV_COLUMNS
from ride_machine.service.cli import main
from ride_machine.service.config.model import EventsSection
from tests.procs import REPO, machine_cmd


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    log = EventLog(tmp_path / EVENTS_FILE, "m1", EventsSection())
    log.start()
    now = time.time()
    log.emit(
        CommandEvent(command="Home", transaction_id="t1", accepted=True, code="RESP_HOME_ACCEPTED"),
        now - 7200,
        5,
    )
    log.emit(DaemonStopEvent(reason="signal SIGTERM", exit_code=0), now, None)
    log.close()
    return tmp_path


def test_jsonl_has_one_event_per_line(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["events", "export", "--data-dir", str(data_dir)]) == 0
    events = [Event.model_validate_json(line) for line in capsys.readouterr().out.splitlines()]
    assert [(e.seq, e.kind) for e in events] == [(1, "command"), (2, "daemon_stop")]


def test_csv_has_a_header_and_the_details_as_json(data_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "events.csv"
    args = ["events", "export", "--data-dir", str(data_dir), "--format", "csv", "-o", str(out)]
    assert main(args) == 0
    rows = list(csv.reader(io.StringIO(out.read_text())))
    assert rows[0] == CSV_COLUMNS
    assert [r[5] for r in rows[1:]] == ["command", "daemon_stop"]
    assert json.loads(rows[1][7])["transaction_id"] == "t1"
    assert rows[1][3] == "5" and rows[2][3] == ""  # the cycle, empty outside the loop
    assert rows[1][6].startswith("Home ") and rows[1][6].endswith("[tx t1]")


def test_since_an_age_and_kind_filter(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["events", "export", "--data-dir", str(data_dir), "--since", "1h"]) == 0
    assert [json.loads(x)["kind"] for x in capsys.readouterr().out.splitlines()] == ["daemon_stop"]
    assert main(["events", "export", "--data-dir", str(data_dir), "--kind", "command"]) == 0
    assert [json.loads(x)["seq"] for x in capsys.readouterr().out.splitlines()] == [1]


def test_bad_input_and_a_missing_database_are_clear_errors(
    data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["events", "export", "--data-dir", str(data_dir), "--since", "soon"]) == 2
    assert "neither a seq number" in capsys.readouterr().err
    assert main(["events", "export", "--data-dir", str(data_dir), "--kind", "bogus"]) == 2
    assert main(["events", "export", "--data-dir", str(tmp_path / "none")]) == 1
    assert "no event log" in capsys.readouterr().err


def test_points_in_the_history() -> None:
    now = 1_000_000.0
    assert parse_point("42", now) == (42, None)
    assert parse_point("7d", now) == (None, now - 7 * 86400)
    assert parse_point("30m", now) == (None, now - 1800)
    seq, when = parse_point("2026-11-27T14:00", now)
    assert seq is None and when is not None
    with pytest.raises(ValueError, match="neither"):
        parse_point("yesterday", now)
    with pytest.raises(ValueError, match="largest seq"):
        parse_point("99999999999999999999999", now)  # SQLite could not even compare it
    with pytest.raises(ValueError, match="neither"):
        parse_point("²", now)  # a digit to str.isdigit, not to int()


def test_an_output_that_cannot_be_written_is_a_clear_error(
    data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "missing" / "events.csv"
    assert main(["events", "export", "--data-dir", str(data_dir), "-o", str(out)]) == 1
    assert capsys.readouterr().err == f"machine: cannot write {out}: No such file or directory\n"


def test_a_corrupt_database_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / EVENTS_FILE).write_bytes(b"garbage " * 1000)
    assert main(["events", "export", "--data-dir", str(tmp_path)]) == 1
    assert "file is not a database" in capsys.readouterr().err


def test_a_reader_that_goes_away_ends_the_export_quietly(tmp_path: Path) -> None:
    log = EventLog(tmp_path / EVENTS_FILE, "m1", EventsSection(queue_capacity=20_000))
    log.start()
    for i in range(5000):  # far more than a pipe buffer holds
        log.emit(DaemonStopEvent(reason="x" * 40, exit_code=0), time.time(), i)
    log.close(timeout=30.0)
    export = subprocess.Popen(
        [*machine_cmd("events", "export", "--data-dir", str(tmp_path))],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
    )
    assert export.stdout is not None and export.stderr is not None
    export.stdout.readline()
    export.stdout.close()  # `| head -1`
    assert export.wait(timeout=30) == 0
    assert export.stderr.read() == b""
