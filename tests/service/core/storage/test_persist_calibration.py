"""Calibration on disk: it survives a restart; a bad file is kept aside and never crashes."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from ride_machine.schema.calibration import CalibrationSource
from ride_machine.schema.commands import Command
from ride_machine.schema.status import MachineState
from ride_machine.service.core.motion.devices import Calibration, RotateCalibration, TiltCalibration
from ride_machine.service.core.storage.persist import (
    CALIBRATION_FILE,
    BackgroundWriter,
    CalibrationStore,
    calibration_to_json,
    load_calibration,
)
from tests.rig import Rig

S = MachineState
CAL = Calibration(
    tilt=TiltCalibration(offset_counts=1194.0, gain_counts_per_deg=40.0),
    rotate=RotateCalibration(revolution_s=4.0, home_arc_deg=9.9),
)


def kept_aside(data_dir: Path) -> list[Path]:
    return sorted(data_dir.glob(f"{CALIBRATION_FILE}.corrupt-*"))


def test_calibration_survives_a_restart(tmp_path: Path) -> None:
    first = Rig(data_dir=tmp_path)
    first.calibrate()
    found = first.state_machine.calibration
    assert (tmp_path / CALIBRATION_FILE).is_file()
    first.hal.close()

    second = Rig(data_dir=tmp_path)

    assert second.state_machine.calibration == found
    assert second.machine.devices.tilt.calibration == found.tilt
    # Calibrated, but never assumed home after a restart, and outputs safe.
    assert second.state is S.WARNING_NOT_HOME
    assert not second.relays_on()
    assert second.state_machine.warnings == []
    status = second.loop.published.status
    assert status is not None
    assert status.calibrated.tilt and status.calibrated.rotate
    # The stored calibration is good enough to run a whole session.
    second.home()
    travel0 = second.hal.world.rotate_travel_deg
    assert second.send(Command.START).success
    second.run_to_state(S.DONE, S.FAULT_HW)
    assert second.state is S.DONE, second.state_machine.fault
    assert second.hal.world.rotate_travel_deg - travel0 == pytest.approx(1080.0, abs=0.9)
    assert second.hal.world.tilt_deg == pytest.approx(45.0, abs=1.0)


def test_a_partial_calibration_survives_as_partial(tmp_path: Path) -> None:
    first = Rig(data_dir=tmp_path)
    assert first.send(Command.CALIBRATE_TILT).success
    first.run_until(lambda: first.state is not S.CALIBRATING)
    assert first.state_machine.calibration.tilt is not None

    second = Rig(data_dir=tmp_path)
    assert second.state_machine.calibration.tilt == first.state_machine.calibration.tilt
    assert second.state_machine.calibration.rotate is None
    assert second.state is S.WARNING_NEEDS_CALIBRATION


def test_recalibration_replaces_the_stored_file(tmp_path: Path) -> None:
    CalibrationStore(tmp_path).save(CAL)
    rig = Rig(data_dir=tmp_path)
    assert rig.state_machine.calibration == CAL
    rig.calibrate()
    assert rig.state_machine.calibration != CAL
    assert Rig(data_dir=tmp_path).state_machine.calibration == rig.state_machine.calibration
    assert list(tmp_path.iterdir()) == [tmp_path / CALIBRATION_FILE]  # no temp files left


CORRUPT = {
    "garbage": b"\x00\xff not json at all",
    "truncated": b'{"version": 1, "tilt": {"offset_counts": 11',
    "empty": b"",
    "not-an-object": b"[1, 2, 3]",
    "wrong-type": json.dumps({"tilt": {"offset_counts": "x", "gain_counts_per_deg": 40}}).encode(),
    "unknown-field": json.dumps({"version": 1, "surprise": True}).encode(),
    "missing-field": json.dumps({"tilt": {"offset_counts": 1.0}}).encode(),
    "zero-gain": json.dumps({"tilt": {"offset_counts": 1.0, "gain_counts_per_deg": 0}}).encode(),
    "nan-gain": b'{"tilt": {"offset_counts": 1194.0, "gain_counts_per_deg": NaN}}',
    "infinite-revolution": b'{"rotate": {"revolution_s": Infinity, "home_arc_deg": 9.9}}',
    "negative-revolution": json.dumps(
        {"rotate": {"revolution_s": -4.0, "home_arc_deg": 10.0}}
    ).encode(),
}


@pytest.mark.parametrize("content", list(CORRUPT.values()), ids=list(CORRUPT))
def test_corrupt_calibration_file_is_kept_aside_with_a_warning(
    tmp_path: Path, content: bytes
) -> None:
    (tmp_path / CALIBRATION_FILE).write_bytes(content)

    rig = Rig(data_dir=tmp_path)

    assert rig.state is S.WARNING_NEEDS_CALIBRATION
    assert rig.state_machine.calibration == Calibration()
    assert not rig.relays_on()
    status = rig.loop.published.status
    assert status is not None
    assert len(status.warnings) == 1
    assert CALIBRATION_FILE in status.warnings[0]
    aside = kept_aside(tmp_path)
    assert len(aside) == 1
    assert aside[0].name in status.warnings[0]
    assert aside[0].read_bytes() == content  # the evidence is kept byte for byte
    assert not (tmp_path / CALIBRATION_FILE).exists()

    # A new calibration writes a fresh file; the kept copy is never overwritten.
    rig.calibrate()
    assert (tmp_path / CALIBRATION_FILE).is_file()
    assert kept_aside(tmp_path) == aside
    assert aside[0].read_bytes() == content
    assert Rig(data_dir=tmp_path).state_machine.calibration == rig.state_machine.calibration


def test_repeated_corruption_keeps_every_copy(tmp_path: Path) -> None:
    path = tmp_path / CALIBRATION_FILE
    for n in range(3):
        path.write_bytes(b"broken %d" % n)
        rig = Rig(data_dir=tmp_path)
        assert rig.state is S.WARNING_NEEDS_CALIBRATION
    aside = kept_aside(tmp_path)
    assert len(aside) == 3
    assert sorted(p.read_bytes() for p in aside) == [b"broken 0", b"broken 1", b"broken 2"]


def test_missing_file_is_not_a_warning(tmp_path: Path) -> None:
    rig = Rig(data_dir=tmp_path / "not-yet")
    assert rig.state is S.WARNING_NEEDS_CALIBRATION
    assert rig.state_machine.warnings == []
    rig.calibrate()
    assert (tmp_path / "not-yet" / CALIBRATION_FILE).is_file()


def test_unreadable_file_is_reported_and_left_alone(tmp_path: Path) -> None:
    (tmp_path / CALIBRATION_FILE).mkdir()  # a directory where the file should be
    calibration, warning = load_calibration(tmp_path)
    assert calibration == Calibration()
    assert warning is not None
    assert "unreadable" in warning
    assert (tmp_path / CALIBRATION_FILE).is_dir()
    assert kept_aside(tmp_path) == []


def test_saved_file_is_readable_json_with_every_value(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path, clock=lambda: 1234.5)
    store.save(CAL)
    doc = json.loads((tmp_path / CALIBRATION_FILE).read_text())
    measured = {"source": "measured", "at": None}
    assert doc["tilt"] == {"offset_counts": 1194.0, "gain_counts_per_deg": 40.0, **measured}
    assert doc["rotate"] == {"revolution_s": 4.0, "home_arc_deg": 9.9, **measured}
    assert doc["saved_at"] == 1234.5
    assert load_calibration(tmp_path) == (CAL, None)
    assert calibration_to_json(Calibration(), 0.0).startswith(b"{")
    assert load_calibration(tmp_path)[0] == CAL


@pytest.mark.hazard("H42")
def test_background_writer_saves_in_order_and_reports_failures(tmp_path: Path) -> None:
    writer = BackgroundWriter(name="test-persist")
    try:
        store = CalibrationStore(tmp_path, writer=writer)
        store.save(Calibration(tilt=CAL.tilt))
        store.save(CAL)
        assert writer.flush(timeout=10)
        assert load_calibration(tmp_path) == (CAL, None)

        blocked = tmp_path / "a-file"
        blocked.write_text("not a directory")
        failing = CalibrationStore(blocked / "sub", writer=writer)
        ticket = failing.save(CAL)
        assert writer.flush(timeout=10)
        assert ticket.done and ticket.problem is not None and "Not a directory" in ticket.problem
        (warning,) = failing.health.warnings()
        assert warning.startswith("STORAGE_FAILED: calibration not saved")
    finally:
        writer.close(timeout=10)


@pytest.mark.hazard("H22", "H23")
def test_a_file_from_before_sources_loads_as_measured_and_manual_values_round_trip(
    tmp_path: Path,
) -> None:
    old = {"version": 1, "tilt": {"offset_counts": 1194.0, "gain_counts_per_deg": 40.0}}
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(old))
    cal, warning = load_calibration(tmp_path)
    assert warning is None and cal.tilt is not None
    assert (cal.tilt.source, cal.tilt.at) == (CalibrationSource.MEASURED, None)
    manual = Calibration(
        tilt=TiltCalibration(1200.0, 41.0, CalibrationSource.MANUAL, 1764300000.0, False),
        rotate=RotateCalibration(4.1, 10.0, CalibrationSource.MEASURED, 1764200000.0),
    )
    CalibrationStore(tmp_path).save(manual)
    assert load_calibration(tmp_path) == (manual, None)
    # A Home verified it since; a start verifies it again (the file may be stale or copied).
    assert manual.tilt is not None
    verified = dataclasses.replace(manual, tilt=dataclasses.replace(manual.tilt, verified=True))
    CalibrationStore(tmp_path).save(verified)
    assert load_calibration(tmp_path) == (manual, None)
    bad = {
        "version": 1,
        "tilt": {"offset_counts": 1.0, "gain_counts_per_deg": 40.0, "source": "guess"},
    }
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(bad))
    assert load_calibration(tmp_path)[0] == Calibration()  # unknown source: not trusted
