"""`rider events` reads for people through a real daemon (issue 58, point 11): a measured rotate
calibration as `rotate calibrated: revolution 4.000 s, home arc 9.9° (measured)`, not a dict of
16-digit floats; the Rider that asked as its login and a short id, not 32 hex digits; the raw
record still whole with `--json`."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.integration.support import fast_daemon, prepare

pytestmark = pytest.mark.integration

ROTATE_TEXT = re.compile(
    r"rotate calibrated: revolution \d+\.\d{3} s, home arc \d+\.\d° \(measured\)$"
)
TILT_TEXT = re.compile(
    r"tilt calibrated: offset -?\d+\.\d counts, gain -?\d+\.\d{3} counts/° \(measured\)$"
)
SHORT_RIDER = re.compile(r"from anonymous · [0-9a-f]{6}\b")
DEBUGGER = re.compile(r"[{}]|\bNone\b|persisted=|[0-9a-f]{16,}|\d\.\d{4,}")


def test_rider_events_reads_calibrations_and_riders_for_people(tmp_path: Path) -> None:
    with fast_daemon(tmp_path) as daemon:
        with daemon.rider() as r:
            prepare(r)  # both calibrations measured, then Home
            zid = r.rider_id.partition("/")[2]
        set_by_cli = daemon.cli("params", "set", "tilt.max_deg", "50.5")
        assert set_by_cli.returncode == 0, set_by_cli.stderr
        shown = daemon.cli("events", "--kind", "calibration,command,safety_changed")
        raw = daemon.cli("events", "--json", "--kind", "calibration,command")
    assert shown.returncode == 0 and raw.returncode == 0, shown.stderr + raw.stderr
    lines = shown.stdout.splitlines()
    calibrations = [line for line in lines if " calibration " in line]
    assert any(ROTATE_TEXT.search(line) for line in calibrations), calibrations
    assert any(TILT_TEXT.search(line) for line in calibrations), calibrations
    commands = [line for line in lines if " command " in line]
    assert any(
        "Calibrate rotate accepted" in line and SHORT_RIDER.search(line) for line in commands
    ), commands
    [param] = [line for line in lines if " safety_changed " in line]
    assert re.search(r"tilt\.max_deg set \d+(\.\d+)?° → 50\.5° by anonymous · [0-9a-f]{6}", param)
    for line in lines:
        assert not DEBUGGER.search(line), line
        assert zid[6:] not in line, line

    # The raw record keeps everything: the whole Rider id, the floats as measured, `at`.
    records = [json.loads(x) for x in raw.stdout.splitlines()]
    rotate = next(e["details"] for e in records if e["details"].get("axis") == "rotate")
    assert {"revolution_s", "home_arc_deg", "source", "at"} <= rotate["new"].keys()
    assert any(e["details"].get("rider", "").endswith(zid) for e in records)
