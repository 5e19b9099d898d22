"""The stores of the data directory: the calibration and the online parameters, written off the
scan thread, and what could not be written, as status warnings (the files themselves are
written and read by service/core/storage/atomic.py)."""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, FiniteFloat, ValidationError

from ride_machine.schema.calibration import CalibrationSource
from ride_machine.schema.errors import ErrorCode
from ride_machine.service.core.motion.devices import Calibration, RotateCalibration, TiltCalibration
from ride_machine.service.threads import NamedThread

from .atomic import atomic_write, load_json, probe_writable, retire, set_aside
from .unsaved import RETRY_S, Unsaved

log = logging.getLogger(__name__)

CALIBRATION_FILE = "calibration.json"


class _TiltEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")

    offset_counts: FiniteFloat  # NaN or infinity means a corrupt file
    gain_counts_per_deg: FiniteFloat
    source: CalibrationSource = CalibrationSource.MEASURED  # files from before: measured
    at: FiniteFloat | None = None


class _RotateEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")

    revolution_s: FiniteFloat
    home_arc_deg: FiniteFloat
    source: CalibrationSource = CalibrationSource.MEASURED
    at: FiniteFloat | None = None


class _CalibrationFile(BaseModel):
    model_config = ConfigDict(extra="forbid")

    version: int = 1
    tilt: _TiltEntry | None = None
    rotate: _RotateEntry | None = None
    saved_at: float | None = None


def calibration_to_json(cal: Calibration, saved_at: float) -> bytes:
    doc = _CalibrationFile(
        tilt=None if cal.tilt is None else _tilt_entry(cal.tilt),
        rotate=None if cal.rotate is None else _RotateEntry(**dataclasses.asdict(cal.rotate)),
        saved_at=saved_at,
    )
    return doc.model_dump_json(indent=2).encode()


def _tilt_entry(tilt: TiltCalibration) -> _TiltEntry:
    """The file's record of the tilt: verification is not stored (a start verifies again)."""
    values = dataclasses.asdict(tilt)
    del values["verified"]
    return _TiltEntry(**values)


def load_calibration(data_dir: Path) -> tuple[Calibration, str | None]:
    """The stored calibration, or an empty one and a warning saying why."""
    path = data_dir / CALIBRATION_FILE
    loaded = load_json(path)
    if loaded.data is None:
        return Calibration(), loaded.warning
    try:
        doc = _CalibrationFile.model_validate(loaded.data)
        # An entered calibration is verified again by the first Home after a start: the file
        # may be stale, copied from another machine, or edited (docs/homing.md).
        tilt = None
        if doc.tilt is not None:
            manual = doc.tilt.source is CalibrationSource.MANUAL
            tilt = TiltCalibration(**doc.tilt.model_dump(), verified=not manual)
        rotate = RotateCalibration(**doc.rotate.model_dump()) if doc.rotate else None
        if tilt is not None and not tilt.gain_counts_per_deg > 0:
            raise ValueError("tilt gain must be positive")
        if rotate is not None and rotate.revolution_s <= 0:
            raise ValueError("revolution time must be positive")
        if rotate is not None and not 0 < rotate.home_arc_deg < 360:
            raise ValueError("home arc must be between 0 and 360 degrees")
    except (ValidationError, TypeError, ValueError) as exc:
        _, where = set_aside(path)
        return Calibration(), (
            f"{path}: invalid calibration ({str(exc).splitlines()[0][:120]}); {where};"
            " using defaults"
        )
    return Calibration(tilt=tilt, rotate=rotate), None


class BackgroundWriter:
    """Runs file writes off the scan thread, in order, so an fsync never costs a cycle."""

    def __init__(self, name: str = "persist") -> None:
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        self._thread = NamedThread(target=self._run, name=name, daemon=True)
        self._thread.start()
        self.failures = 0

    def submit(self, job: Callable[[], None]) -> None:
        self._jobs.put(job)

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every submitted write is done."""
        done = threading.Event()
        self._jobs.put(done.set)
        return done.wait(timeout)

    def close(self, timeout: float = 5.0) -> None:
        self._jobs.put(None)
        self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            except OSError as exc:
                self.failures += 1
                log.error("event=persist_failed error=%r", str(exc))


STORAGE_FAILED = ErrorCode.STORAGE_FAILED.value
"""The prefix of every status warning about a value that could not be written (the wire code)."""


class StorageHealth:
    """What could not be written to the data directory, as status warnings (thread-safe).

    Writers report here: the start-up probe, the calibration store, the parameter registry.
    A later successful write proves the directory works again: it clears its own writer's
    warning and the data dir's, never another writer's (that value is still not on disk).
    """

    DATA_DIR = "data_dir"
    CALIBRATION = "calibration"
    PARAMS = "params"

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._problems: dict[str, str] = {}
        self.version = 0
        """Counts changes, so the scan loop republishes status when the warnings change."""

    def failed(self, what: str, message: str) -> None:
        with self._lock:
            self._problems[what] = f"{STORAGE_FAILED}: {message}"
            self.version += 1

    def recovered(self, what: str) -> None:
        """Writer `what` has written: its warning and the data dir's go (another writer's
        stays: a calibration still unsaved is not saved by a parameter write)."""
        with self._lock:
            gone = [k for k in (what, self.DATA_DIR) if self._problems.pop(k, None) is not None]
            if gone:
                self.version += 1

    def warnings(self) -> list[str]:
        with self._lock:
            return list(self._problems.values())


FULL = (errno.ENOSPC, errno.EDQUOT)
"""A full disk still renames: a failed save there moved the older file aside already."""


class SaveTicket:
    """The outcome of one background write; the scan thread polls `done` (no lock, no wait)."""

    def __init__(self) -> None:
        self._done = threading.Event()
        self.problem: str | None = None

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def wait(self, timeout: float) -> bool:
        """Block (never on the scan thread) until the write is done; False after `timeout`."""
        return self._done.wait(timeout)

    def finish(self, problem: str | None) -> None:
        self.problem = problem
        self._done.set()


class CalibrationStore:
    """The calibration file in the data directory; writes go through a background writer.

    A save that fails never leaves an older file to be loaded as current: the older file is
    moved aside (`calibration.json.stale-<time>`), and the new calibration is saved as soon as
    the directory takes it (service/core/storage/unsaved.py: while the machine runs, and as it
    stops). Where even the move fails (a read-only mount), a start that finds the directory
    still not writable does not trust the file. What cannot hold: a machine killed (or a power cut)
    before any retry succeeds, then started with the directory writable again, loads the
    older file; the refusal says so, with its values.
    """

    def __init__(
        self,
        data_dir: Path,
        writer: BackgroundWriter | None = None,
        clock: Callable[[], float] = time.time,
        health: StorageHealth | None = None,
    ) -> None:
        self.data_dir = data_dir
        self.writer = writer
        self.clock = clock
        self.health = health or StorageHealth()
        self.unsaved = Unsaved(
            lambda data: atomic_write(self.path, data),
            writer.submit if writer is not None else None,
            lambda: self.health.recovered(StorageHealth.CALIBRATION),
        )
        """A calibration that could not be saved, tried again."""

    @property
    def path(self) -> Path:
        return self.data_dir / CALIBRATION_FILE

    def load(self) -> tuple[Calibration, str | None]:
        """The stored calibration; from a directory that cannot be written, none (and why)."""
        problem = probe_writable(self.data_dir)
        if problem is None:
            return load_calibration(self.data_dir)
        message = (
            f"data dir {self.data_dir} is not writable ({problem.strerror or problem});"
            " calibration and persistent parameters cannot be saved"
        )
        trusted = problem.errno in FULL or not self.path.exists()
        if not trusted:
            # A calibration that failed to save there could not move this file aside either.
            message += f"; {self.path.name} is not trusted as current: calibrate again"
        self.health.failed(StorageHealth.DATA_DIR, message)
        log.error("event=data_dir_not_writable detail=%r", message)
        return load_calibration(self.data_dir) if trusted else (Calibration(), None)

    def save(self, cal: Calibration) -> SaveTicket:
        """Write `cal` (in the background when there is a writer); the ticket says how it went."""
        data = calibration_to_json(cal, self.clock())
        ticket = SaveTicket()

        def job() -> None:
            self.unsaved.drop()  # this one supersedes any calibration still waiting
            try:
                atomic_write(self.path, data)
            except OSError as exc:
                ticket.finish(self._failed(exc, data))
                return
            self.health.recovered(StorageHealth.CALIBRATION)
            ticket.finish(None)

        if self.writer is None:
            job()
        else:
            self.writer.submit(job)
        return ticket

    def _failed(self, exc: OSError, data: bytes) -> str:
        why = exc.strerror or str(exc)
        try:
            stale = retire(self.path)
        except OSError as retire_exc:
            self.unsaved.keep(data)
            message = (
                f"calibration not saved to {self.path} ({why}), and the older file could not be"
                f" moved aside ({retire_exc.strerror or retire_exc}); it holds {_holds(self.path)}."
                f" The new calibration is in use; it is saved as soon as the data dir takes it"
                f" (tried every {RETRY_S:g} s and as the machine stops). A start while the dir"
                " cannot be written does not trust the older file; a start after the machine"
                " was killed before any of these succeeded, with the dir writable again, loads"
                " the older file as current: calibrate again then"
            )
        else:
            # A full disk frees up (a log rotated, a file removed): nothing else would save it.
            self.unsaved.keep(data)
            older = f"the older file was moved aside to {stale.name}" if stale else "no older file"
            message = (
                f"calibration not saved to {self.path} ({why}); {older}. The new calibration is"
                f" in use; it is saved as soon as the data dir takes it (tried every {RETRY_S:g} s"
                " and as the machine stops), and lost at a restart before then"
            )
        self.health.failed(StorageHealth.CALIBRATION, message)
        log.error("event=persist_failed what=calibration error=%r detail=%r", why, message)
        return message

    def close(self) -> None:
        """As the machine stops: the last try at a calibration not saved yet (said if it
        fails: the next start's trust in the older file depends on the dir)."""
        self.unsaved.stop()
        if self.writer is not None:
            self.writer.submit(self.unsaved.retry)  # in order after any save under way
            self.writer.flush()
        else:
            self.unsaved.retry()
        if self.unsaved.pending:
            detail = (
                f"the older file ({_holds(self.path)}) is loaded as current by a start that"
                " finds the data dir writable"
                if self.path.exists()
                else "the next start needs calibration"
            )
            log.error("event=calibration_unsaved_at_stop path=%s detail=%r", self.path, detail)


def _holds(path: Path) -> str:
    """What a calibration file says, for a message (read only: nothing is moved or removed)."""
    try:
        doc = _CalibrationFile.model_validate_json(path.read_bytes())
    except (OSError, ValidationError):
        return "no calibration that could be read"
    parts = []
    if doc.tilt is not None:
        t = doc.tilt
        parts.append(f"tilt gain {t.gain_counts_per_deg:g} counts/°, offset {t.offset_counts:g}")
    if doc.rotate is not None:
        parts.append(f"rotate {doc.rotate.revolution_s:g} s per revolution")
    return ", ".join(parts) or "no calibration"


PARAMS_FILE = "params.json"
PARAMS_VERSION = 1

ParamScalar = float | int | bool | str


@dataclass(frozen=True)
class StoredParam:
    """One persisted override: the value and when it was written online (wall time)."""

    value: ParamScalar
    changed_at: float | None = None


class _ParamEntry(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    value: ParamScalar
    changed_at: float | None = None


class _ParamsFile(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    version: int
    params: dict[str, Any]


class ParamStore:
    """The persisted parameter overrides, `params.json` in the data directory.

    Only values written with `persist: true` are here; everything else is the project default.
    """

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir

    @property
    def path(self) -> Path:
        return self.data_dir / PARAMS_FILE

    def load(self) -> tuple[dict[str, StoredParam], list[str]]:
        """The stored overrides, and a warning per thing that was wrong (never raises)."""
        loaded = load_json(self.path)
        if loaded.data is None:
            return {}, [loaded.warning] if loaded.warning else []
        try:
            doc = _ParamsFile.model_validate(loaded.data)
            if doc.version != PARAMS_VERSION:
                raise ValueError(f"version {doc.version} is not {PARAMS_VERSION}")
        except (ValidationError, ValueError) as exc:
            _, where = set_aside(self.path)
            return {}, [
                f"{self.path}: invalid parameter file ({str(exc).splitlines()[0][:120]});"
                f" {where}; using defaults"
            ]
        out: dict[str, StoredParam] = {}
        warnings = []
        for name, raw in doc.params.items():
            try:
                entry = _ParamEntry.model_validate(raw)
            except ValidationError as exc:
                first = exc.errors(include_url=False)[0]
                warnings.append(
                    f"{self.path}: parameter {name!r} ignored ({first['msg']}); using the default"
                )
                continue
            out[name] = StoredParam(entry.value, entry.changed_at)
        return out, warnings

    def save(self, params: Mapping[str, StoredParam]) -> None:
        """Write every override at once, atomically (raises OSError if the disk refuses)."""
        doc = {
            "version": PARAMS_VERSION,
            "params": {
                name: {"value": p.value, "changed_at": p.changed_at}
                for name, p in sorted(params.items())
            },
        }
        atomic_write(self.path, (json.dumps(doc, indent=2, allow_nan=False) + "\n").encode())
