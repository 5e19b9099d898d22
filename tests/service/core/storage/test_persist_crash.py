"""Crash safety of the stores: SIGKILL mid-write never tears a file; corrupt files never crash."""

from __future__ import annotations

import errno
import os
import random
import subprocess
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest

from ride_machine.schema.params import ParamSet
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.devices import Calibration
from ride_machine.service.core.storage.atomic import (
    atomic_write,
    keep_aside,
    load_json,
    remove_stale_temps,
)
from ride_machine.service.core.storage.params import ParamRegistry
from ride_machine.service.core.storage.persist import (
    CALIBRATION_FILE,
    PARAMS_FILE,
    CalibrationStore,
    ParamStore,
    load_calibration,
)
from tests.rig import Rig
from tests.service.core.storage import persist_crash_writer as writer
from tests.service.crash import CrashServer

KILLS = 200
BOUND_S = 120.0  # a bound so a hung child fails the test instead of hanging it, not a speed check


def _index(value: object, r: int, of: Callable[[int], float]) -> int:
    """Which round (r or r + 1) wrote `value`; anything else is a torn or lost write."""
    for i in (r, r + 1):
        if value == of(i):
            return i
    raise AssertionError(f"value {value!r} is from neither round {r} nor {r + 1}")


def _check(data_dir: Path, r: int) -> tuple[int, int, int]:
    """Load through the daemon's own code; every file must hold round r's or r+1's value."""
    registry = ParamRegistry(MachineConfig(), ParamStore(data_dir))
    assert registry.warnings == []
    cal, warning = CalibrationStore(data_dir).load()
    assert warning is None
    first = registry.get(writer.FIRST)
    second = registry.get(writer.SECOND)
    assert first.persisted and second.persisted
    i1 = _index(first.value, r, writer.first_value)
    i2 = _index(second.value, r, writer.second_value)
    assert cal.tilt is not None and cal.rotate is not None
    ic = _index(cal.tilt.offset_counts, r, float)
    assert (first.changed_at, second.changed_at) == (float(i1), float(i2))
    # One round writes FIRST, SECOND, calibration in that order: a later file is never newer.
    assert i1 >= i2 >= ic, (i1, i2, ic)
    left = sorted(p.name for p in data_dir.iterdir())
    assert left == [CALIBRATION_FILE, PARAMS_FILE], left  # no temp file, nothing kept aside
    return i1 - r, i2 - r, ic - r


@pytest.mark.hazard("H40", "H43")
@pytest.mark.integration
def test_sigkill_at_random_moments_never_leaves_a_torn_file(tmp_path: Path) -> None:
    seed = int.from_bytes(os.urandom(4), "big")
    rng = random.Random(seed)
    outcomes: Counter[tuple[int, int, int]] = Counter()
    mid_write = 0
    with CrashServer([sys.executable, writer.__file__, str(tmp_path)], "w", BOUND_S) as server:
        start = 1
        for _ in range(KILLS):
            # Kill after a random number of complete rounds, at a random point of the next.
            last = server.kill_round(start, rng.randint(1, 4), rng.uniform(0.0, 0.002))
            mid_write += any(p.name.endswith(".tmp") for p in tmp_path.iterdir())
            outcome = _check(tmp_path, last)
            outcomes[outcome] += 1
            start = last + max(outcome) + 1
    print(f"seed={seed} kills={KILLS} mid_write={mid_write} outcomes={dict(outcomes)}")
    assert sum(outcomes.values()) == KILLS
    # The kills really landed inside writes and at different points of a round.
    assert mid_write > 0
    assert len(outcomes) >= 2


# ------------------------------------------------------------------ corrupt at start-up
CORRUPT = b'{"version": 1, "params": {"tilt.tolerance_deg": {"value": 2.'


def _kept(data_dir: Path, name: str) -> list[Path]:
    return sorted(data_dir.glob(f"{name}.corrupt-*"))


@pytest.mark.hazard("H40")
def test_corrupt_params_file_gives_warning_and_defaults_and_is_kept(tmp_path: Path) -> None:
    (tmp_path / PARAMS_FILE).write_bytes(CORRUPT)
    registry = ParamRegistry(MachineConfig(), ParamStore(tmp_path))
    assert len(registry.warnings) == 1
    assert "corrupt" in registry.warnings[0] and "using defaults" in registry.warnings[0]
    assert registry.get("tilt.tolerance_deg").value == 1.0
    assert registry.config == MachineConfig()
    [kept] = _kept(tmp_path, PARAMS_FILE)
    assert kept.read_bytes() == CORRUPT
    assert kept.name in registry.warnings[0]
    # The next persisted write starts a new file and leaves the kept one alone.
    registry.set(
        "tilt.tolerance_deg",
        ParamSet(transaction_id="t", value=3.0, persist=True),
        moving=False,
        now=1.0,
    )
    assert kept.read_bytes() == CORRUPT
    assert ParamRegistry(MachineConfig(), ParamStore(tmp_path)).get("tilt.tolerance_deg").value == 3


@pytest.mark.parametrize(
    "doc",
    [b"[1, 2]", b'{"version": 1, "params": []}', b'{"version": 7, "params": {}}', b"\xff\xfe"],
    ids=["not-an-object", "params-not-a-table", "unknown-version", "not-utf8"],
)
def test_params_file_of_wrong_shape_is_kept_aside(tmp_path: Path, doc: bytes) -> None:
    (tmp_path / PARAMS_FILE).write_bytes(doc)
    registry = ParamRegistry(MachineConfig(), ParamStore(tmp_path))
    [warning] = registry.warnings
    assert "kept as" in warning
    assert [p.read_bytes() for p in _kept(tmp_path, PARAMS_FILE)] == [doc]
    assert not (tmp_path / PARAMS_FILE).exists()
    assert all(not p.persisted for p in registry.list())


def test_corrupt_calibration_file_gives_warning_and_defaults_and_is_kept(tmp_path: Path) -> None:
    bad = b'{"version": 1, "tilt": {"offset_counts": 12'
    (tmp_path / CALIBRATION_FILE).write_bytes(bad)
    cal, warning = CalibrationStore(tmp_path).load()
    assert cal == Calibration()
    assert warning is not None and "corrupt" in warning
    [kept] = _kept(tmp_path, CALIBRATION_FILE)
    assert kept.read_bytes() == bad
    assert kept.name in warning


@pytest.mark.hazard("H40")
def test_machine_starts_needing_calibration_on_a_corrupt_calibration_file(
    tmp_path: Path,
) -> None:
    (tmp_path / CALIBRATION_FILE).write_bytes(b"\x00\x00garbage")
    rig = Rig(data_dir=tmp_path)
    assert rig.state is MachineState.WARNING_NEEDS_CALIBRATION
    assert any("corrupt" in w for w in rig.state_machine.warnings)
    assert not rig.relays_on()
    assert [p.read_bytes() for p in _kept(tmp_path, CALIBRATION_FILE)] == [b"\x00\x00garbage"]


@pytest.mark.hazard("H40")
def test_invalid_calibration_values_are_kept_aside(tmp_path: Path) -> None:
    doc = b'{"version": 1, "tilt": {"offset_counts": 1.0, "gain_counts_per_deg": 0.0}}'
    (tmp_path / CALIBRATION_FILE).write_bytes(doc)
    cal, warning = CalibrationStore(tmp_path).load()
    assert cal == Calibration()
    assert warning is not None and "gain must be positive" in warning
    assert [p.read_bytes() for p in _kept(tmp_path, CALIBRATION_FILE)] == [doc]


def test_keep_aside_never_overwrites_an_earlier_kept_file(tmp_path: Path) -> None:
    path = tmp_path / PARAMS_FILE
    kept = []
    for content in (b"one", b"two", b"three"):
        path.write_bytes(content)
        kept.append(keep_aside(path))
    assert len(set(kept)) == 3
    assert [k.read_bytes() for k in kept] == [b"one", b"two", b"three"]


def read_only_fs(*args: object, **kwargs: object) -> None:
    """What `os.replace` and `os.unlink` do on a read-only mount."""
    raise OSError(errno.EROFS, "Read-only file system")


def _dead_pid() -> int:
    """The pid of a process that has ended: a writer that died mid-write."""
    done = subprocess.run(["sh", "-c", "echo $$"], capture_output=True, check=True, timeout=60)
    return int(done.stdout)


@pytest.mark.parametrize(
    "doc", [b'{"version": 1, "par', b'{"version": 7, "params": {}}'], ids=["torn", "wrong-version"]
)
@pytest.mark.hazard("H39")
def test_a_bad_params_file_on_a_read_only_dir_is_a_warning_not_a_failed_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, doc: bytes
) -> None:
    """Moving the file aside (and a dead writer's temp file away) raised EROFS out of the
    load, and the daemon did not start."""
    (tmp_path / PARAMS_FILE).write_bytes(doc)
    stale = tmp_path / f".{PARAMS_FILE}.{_dead_pid()}.1.tmp"
    stale.write_bytes(b"{")
    monkeypatch.setattr(os, "replace", read_only_fs)
    monkeypatch.setattr(os, "unlink", read_only_fs)
    registry = ParamRegistry(MachineConfig(), ParamStore(tmp_path))
    monkeypatch.undo()
    [warning] = registry.warnings
    assert "could not be kept aside (Read-only file system), left in place" in warning
    assert warning.endswith("using defaults")
    assert (tmp_path / PARAMS_FILE).read_bytes() == doc and stale.exists()
    assert all(not p.persisted for p in registry.list())


@pytest.mark.hazard("H39")
def test_an_invalid_calibration_on_a_read_only_dir_is_a_warning_and_defaults(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    doc = b'{"version": 1, "tilt": {"offset_counts": 1.0, "gain_counts_per_deg": 0.0}}'
    (tmp_path / CALIBRATION_FILE).write_bytes(doc)
    monkeypatch.setattr(os, "replace", read_only_fs)
    cal, warning = load_calibration(tmp_path)
    monkeypatch.undo()
    assert cal == Calibration()
    assert warning is not None and "could not be kept aside" in warning
    assert (tmp_path / CALIBRATION_FILE).read_bytes() == doc


def test_unreadable_file_is_reported_not_moved(tmp_path: Path) -> None:
    (tmp_path / PARAMS_FILE).mkdir()  # a directory where the file should be: unreadable
    loaded = load_json(tmp_path / PARAMS_FILE)
    assert loaded.data is None and loaded.warning is not None and "unreadable" in loaded.warning
    assert (tmp_path / PARAMS_FILE).is_dir()


# ------------------------------------------------------------------------ temp files
@pytest.mark.hazard("H40")
def test_temp_files_of_dead_writers_are_removed_at_load(tmp_path: Path) -> None:
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        check=True,
        timeout=60,
    )
    dead_pid = int(dead.stdout)
    path = tmp_path / PARAMS_FILE
    stale = tmp_path / f".{PARAMS_FILE}.{dead_pid}.1.tmp"
    mine = tmp_path / f".{PARAMS_FILE}.{os.getpid()}.1.tmp"
    other = tmp_path / f".{CALIBRATION_FILE}.{dead_pid}.1.tmp"
    for p in (stale, mine, other):
        p.write_bytes(b"{")
    assert remove_stale_temps(path) == [stale]
    assert not stale.exists() and mine.exists() and other.exists()


def test_failed_write_leaves_no_temp_file_and_the_old_file_intact(tmp_path: Path) -> None:
    target = tmp_path / "params.json"
    target.mkdir()
    (target / "x").write_bytes(b"")  # a non-empty directory: the rename must fail
    with pytest.raises(OSError):
        atomic_write(target, b"{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.json"]


def test_a_failed_write_says_its_own_error_not_the_cleanup_s(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The temp file was never made: removing it (EROFS on a read-only mount) must not hide
    why the write failed."""

    def refused(*args: object, **kwargs: object) -> int:
        raise OSError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(os, "open", refused)
    monkeypatch.setattr(os, "unlink", read_only_fs)
    with pytest.raises(PermissionError):
        atomic_write(tmp_path / PARAMS_FILE, b"{}")


def test_atomic_write_creates_the_data_directory(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "calibration.json"
    atomic_write(path, b'{"x": 1}')
    assert path.read_bytes() == b'{"x": 1}'
