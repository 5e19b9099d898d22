"""No silent loss: a calibration or parameter that cannot be written is never reported saved,
and an older file is never loaded as current after a failed save (injected write failures;
the real full and read-only filesystems are in tests/integration/test_storage_failed.py)."""

from __future__ import annotations

import errno
import json
import os
from collections.abc import Callable
from pathlib import Path

import pytest

from ride_machine.schema.calibration import CalibrationSet, TiltCalibrationSet
from ride_machine.schema.commands import Command
from ride_machine.schema.events import CalibrationEvent
from ride_machine.schema.params import ParamSet
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.history.events import ListEventSink
from ride_machine.service.core.motion.devices import Calibration, RotateCalibration, TiltCalibration
from ride_machine.service.core.storage.atomic import NotDurable, atomic_write
from ride_machine.service.core.storage.params import ParamRegistry
from ride_machine.service.core.storage.persist import (
    CALIBRATION_FILE,
    PARAMS_FILE,
    CalibrationStore,
    ParamStore,
    SaveTicket,
    StorageHealth,
    calibration_to_json,
)
from ride_machine.service.errors import StorageFailed
from tests.rig import Rig

S = MachineState
OLD = Calibration(
    tilt=TiltCalibration(offset_counts=1190.0, gain_counts_per_deg=39.0),  # within the scale
    rotate=RotateCalibration(revolution_s=4.0, home_arc_deg=9.9),
)


def disk_full(path: Path, data: bytes) -> None:
    raise OSError(errno.ENOSPC, "No space left on device")


def read_only(path: Path) -> Path:
    raise OSError(errno.EROFS, "Read-only file system")


@pytest.mark.hazard("H22", "H38")
def test_a_failed_calibration_save_is_a_warning_and_the_older_file_goes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / CALIBRATION_FILE).write_bytes(calibration_to_json(OLD, 1.0))
    rig = Rig(data_dir=tmp_path)
    assert rig.state_machine.calibration == OLD
    monkeypatch.setattr("ride_machine.service.core.storage.persist.atomic_write", disk_full)

    assert rig.send(Command.CALIBRATE_TILT).success
    rig.run_until(lambda: rig.state is not S.CALIBRATING)

    status = rig.loop.build_status(rig.clock())
    (warning,) = status.warnings
    assert warning.startswith("STORAGE_FAILED: calibration not saved")
    assert "No space left" in warning and "moved aside" in warning
    assert status.calibrated.tilt  # usable for this run, and said to be unsaved
    assert not (tmp_path / CALIBRATION_FILE).exists()
    assert len(list(tmp_path.glob(f"{CALIBRATION_FILE}.stale-*"))) == 1

    monkeypatch.undo()
    restarted = Rig(data_dir=tmp_path)
    assert restarted.state_machine.calibration == Calibration()  # not the older one
    assert restarted.state is S.WARNING_NEEDS_CALIBRATION


def calibration_events(sink: ListEventSink) -> list[CalibrationEvent]:
    return [d for d, _, _ in sink.events if isinstance(d, CalibrationEvent)]


@pytest.mark.parametrize("disk", ["full", "fine"])
def test_the_history_says_whether_a_calibration_was_saved(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, disk: str
) -> None:
    """Issue 37: a calibration whose save failed was recorded `persisted=True`. The event now
    waits for the write to end, measured or entered by hand."""
    sink = ListEventSink()
    rig = Rig(data_dir=tmp_path, events=sink)
    if disk == "full":
        monkeypatch.setattr("ride_machine.service.core.storage.persist.atomic_write", disk_full)
    assert rig.send(Command.CALIBRATE_TILT).success
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    cal = rig.state_machine.calibration.tilt
    assert cal is not None
    entered = TiltCalibrationSet(offset_counts=cal.offset_counts + 4, gain_counts_per_deg=40.0)
    rig.state_machine.enter_calibration(
        CalibrationSet(transaction_id="c1", tilt=entered), rig.clock()
    )
    rig.run_until(lambda: len(calibration_events(sink)) == 2, max_s=5)
    measured, manual = calibration_events(sink)
    assert measured.new is not None and manual.new is not None
    assert (measured.new["source"], manual.new["source"]) == ("measured", "manual")
    assert measured.persisted is manual.persisted is (disk == "fine")


def test_a_later_good_save_clears_the_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rig = Rig(data_dir=tmp_path)
    monkeypatch.setattr("ride_machine.service.core.storage.persist.atomic_write", disk_full)
    assert rig.send(Command.CALIBRATE_TILT).success
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    assert rig.loop.build_status(rig.clock()).warnings
    monkeypatch.undo()
    assert rig.send(Command.CALIBRATE_TILT).success
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    assert rig.loop.build_status(rig.clock()).warnings == []
    assert (tmp_path / CALIBRATION_FILE).is_file()


class SlowStore:
    """A store whose write the test finishes by hand (a background writer's fsync)."""

    def __init__(self) -> None:
        self.tickets: list[SaveTicket] = []

    def load(self) -> tuple[Calibration, str | None]:
        return Calibration(), None

    def save(self, cal: Calibration) -> SaveTicket:
        self.tickets.append(SaveTicket())
        return self.tickets[-1]


@pytest.mark.hazard("H38")
def test_calibration_ends_only_when_the_disk_has_answered() -> None:
    rig = Rig()
    store = SlowStore()
    rig.state_machine.keeper.on_calibrated = store.save
    assert rig.send(Command.CALIBRATE_TILT).success
    rig.run_until(lambda: bool(store.tickets))
    rig.step(50)
    assert rig.state is S.CALIBRATING  # measured, but not yet saved
    assert rig.state_machine.context.drive.controller is None and not rig.relays_on()
    store.tickets[0].finish("disk on fire")
    rig.step()
    assert rig.state is S.WARNING_NEEDS_CALIBRATION  # rotate is still to calibrate
    assert "NOT saved" in rig.transitions[-1].reason


@pytest.mark.hazard("H39")
def test_a_data_dir_that_cannot_be_written_is_a_warning_from_start(tmp_path: Path) -> None:
    blocked = tmp_path / "a-file"
    blocked.write_text("not a directory")
    rig = Rig(data_dir=blocked / "data")
    warnings = rig.loop.build_status(rig.clock()).warnings
    assert [w for w in warnings if w.startswith("STORAGE_FAILED: data dir")], warnings
    assert "not writable (Not a directory)" in warnings[-1]


def refused_after_a_good_write(
    registry: ParamRegistry,
    monkeypatch: pytest.MonkeyPatch,
    where: str,
    failure: Callable[..., None],
    match: str,
) -> str:
    """A parameter persisted as 2.0, then its write of 3.0 refused by `failure` (patched in at
    `where`, taken out again); the parameter's name."""
    name = "bus.heartbeat_s"
    registry.set(name, ParamSet(transaction_id="p1", value=2.0, persist=True), moving=False, now=1)
    monkeypatch.setattr(where, failure)
    with pytest.raises(StorageFailed, match=match):
        req = ParamSet(transaction_id="p2", value=3.0, persist=True)
        registry.set(name, req, moving=False, now=2)
    monkeypatch.undo()
    return name


@pytest.mark.hazard("H38")
def test_a_failed_parameter_write_changes_nothing_and_is_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    health = StorageHealth()
    store = ParamStore(tmp_path)
    registry = ParamRegistry(MachineConfig(), store, health)
    where = "ride_machine.service.core.storage.persist.atomic_write"
    name = refused_after_a_good_write(registry, monkeypatch, where, disk_full, "No space left")
    assert registry.get(name).value == 2.0
    (warning,) = health.warnings()
    assert warning.startswith(f"STORAGE_FAILED: {name}: could not write")
    saved = json.loads(store.path.read_text())
    assert saved["params"][name]["value"] == 2.0  # the file matches what runs


@pytest.mark.hazard("H39")
def test_a_calibration_whose_older_file_cannot_be_moved_aside_is_saved_once_it_can(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 43, point 4: neither the save nor the move aside works (a read-only dir): the new
    calibration is written as soon as the dir takes it, here as the store closes; the refusal
    said what the older file holds and what a kill before that would load."""
    (tmp_path / CALIBRATION_FILE).write_bytes(calibration_to_json(OLD, 1.0))
    store = CalibrationStore(tmp_path)  # no writer: saves at once, the last try at `close`
    monkeypatch.setattr("ride_machine.service.core.storage.persist.atomic_write", disk_full)

    monkeypatch.setattr("ride_machine.service.core.storage.persist.retire", read_only)
    new = Calibration(tilt=TiltCalibration(offset_counts=1194.0, gain_counts_per_deg=50.0))
    ticket = store.save(new)
    assert ticket.done and ticket.problem is not None
    assert "could not be moved aside" in ticket.problem
    assert "tilt gain 39 counts/°" in ticket.problem  # what the older file holds
    assert "loads the older file as current" in ticket.problem  # what a kill would do
    assert store.unsaved.pending
    monkeypatch.undo()  # writable again
    store.close()
    assert not store.unsaved.pending and store.health.warnings() == []
    cal, problem = CalibrationStore(tmp_path).load()
    assert problem is None and cal.tilt is not None and cal.tilt.gain_counts_per_deg == 50.0


def test_a_newer_save_replaces_a_calibration_still_waiting(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / CALIBRATION_FILE).write_bytes(calibration_to_json(OLD, 1.0))
    store = CalibrationStore(tmp_path)
    monkeypatch.setattr("ride_machine.service.core.storage.persist.atomic_write", disk_full)
    monkeypatch.setattr("ride_machine.service.core.storage.persist.retire", read_only)
    store.save(Calibration(tilt=TiltCalibration(offset_counts=1.0, gain_counts_per_deg=50.0)))
    monkeypatch.undo()
    newest = Calibration(tilt=TiltCalibration(offset_counts=2.0, gain_counts_per_deg=44.0))
    assert store.save(newest).problem is None
    assert not store.unsaved.pending
    store.close()
    cal, _ = CalibrationStore(tmp_path).load()
    assert cal.tilt is not None and cal.tilt.gain_counts_per_deg == 44.0


def sync_failed(path: Path) -> None:
    raise OSError(errno.EIO, "Input/output error")


@pytest.mark.hazard("H38")
def test_a_parameter_refused_after_its_rename_leaves_the_file_as_the_reply_says(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The directory's fsync failed after the rename: refused "nothing was changed", and the
    new value was in the file all the same, to apply itself at the next start."""
    store = ParamStore(tmp_path)
    registry = ParamRegistry(MachineConfig(), store, StorageHealth())
    where = "ride_machine.service.core.storage.atomic.fsync_dir"
    name = refused_after_a_good_write(registry, monkeypatch, where, sync_failed, "Input/output")
    assert registry.get(name).value == 2.0
    assert json.loads(store.path.read_text())["params"][name]["value"] == 2.0
    assert ParamRegistry(MachineConfig(), ParamStore(tmp_path)).get(name).value == 2.0
    assert [p.name for p in tmp_path.iterdir()] == [PARAMS_FILE]  # no temp file left


def test_a_first_file_whose_directory_sync_fails_is_taken_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("ride_machine.service.core.storage.atomic.fsync_dir", sync_failed)
    with pytest.raises(OSError, match="Input/output error"):
        atomic_write(tmp_path / PARAMS_FILE, b"{}")
    assert list(tmp_path.iterdir()) == []


def test_a_new_file_that_cannot_be_taken_back_is_said_not_durable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The sync failed and putting the older file back failed too: the caller learns that the
    new file is the one in place."""
    path = tmp_path / PARAMS_FILE
    path.write_bytes(b"old")
    renames: list[object] = []
    real_replace = os.replace

    def first_rename_only(src: str, dst: str) -> None:
        renames.append(src)
        if len(renames) > 1:
            raise OSError(errno.EIO, "Input/output error")
        real_replace(src, dst)

    monkeypatch.setattr("ride_machine.service.core.storage.atomic.fsync_dir", sync_failed)
    monkeypatch.setattr(os, "replace", first_rename_only)
    with pytest.raises(NotDurable, match="could not be taken back"):
        atomic_write(path, b"new")
    monkeypatch.undo()
    assert path.read_bytes() == b"new"


@pytest.mark.hazard("H38")
def test_a_parameter_whose_file_cannot_be_taken_back_is_taken_and_its_doubt_said(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`NotDurable`: the new file is the one read now, so the registry takes the value the file
    has and says a power cut may lose it, instead of refusing what is already on disk."""
    health = StorageHealth()
    store = ParamStore(tmp_path)
    registry = ParamRegistry(MachineConfig(), store, health)

    def not_durable(path: Path, data: bytes) -> None:
        path.write_bytes(data)
        raise NotDurable(errno.EIO, "Input/output error")

    monkeypatch.setattr("ride_machine.service.core.storage.persist.atomic_write", not_durable)
    req = ParamSet(transaction_id="p1", value=2.0, persist=True)
    registry.set("bus.heartbeat_s", req, moving=False, now=1)
    monkeypatch.undo()
    assert registry.get("bus.heartbeat_s").value == 2.0
    assert json.loads(store.path.read_text())["params"]["bus.heartbeat_s"]["value"] == 2.0
    (warning,) = health.warnings()
    assert "could not be synced" in warning and "a power cut may lose it" in warning


@pytest.mark.parametrize("branch", ["full", "read-only"])
@pytest.mark.hazard("H38")
def test_a_calibration_refused_by_the_disk_keeps_its_warning_until_it_is_saved(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, branch: str
) -> None:
    """On a full disk nothing tried the calibration again, and a parameter written once there
    was room cleared its warning: the status said all was saved when it was not."""
    (tmp_path / CALIBRATION_FILE).write_bytes(calibration_to_json(OLD, 1.0))
    health = StorageHealth()
    store = CalibrationStore(tmp_path, health=health)  # no writer: tried again by hand below
    registry = ParamRegistry(MachineConfig(), ParamStore(tmp_path), health)
    monkeypatch.setattr("ride_machine.service.core.storage.persist.atomic_write", disk_full)
    if branch == "read-only":
        monkeypatch.setattr("ride_machine.service.core.storage.persist.retire", read_only)
    new = Calibration(tilt=TiltCalibration(offset_counts=1194.0, gain_counts_per_deg=50.0))
    ticket = store.save(new)
    assert ticket.problem is not None and "saved as soon as the data dir takes it" in ticket.problem
    assert store.unsaved.pending
    monkeypatch.undo()  # room again

    req = ParamSet(transaction_id="p1", value=2.0, persist=True)
    registry.set("bus.heartbeat_s", req, moving=False, now=1)
    (warning,) = health.warnings()
    assert warning.startswith("STORAGE_FAILED: calibration not saved")

    store.unsaved.retry()  # what the retry thread runs every RETRY_S on the store's writer
    assert not store.unsaved.pending and health.warnings() == []
    cal, problem = CalibrationStore(tmp_path).load()
    assert problem is None and cal.tilt is not None and cal.tilt.gain_counts_per_deg == 50.0
