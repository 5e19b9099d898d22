"""Files that must survive a crash: atomic writes, loads that never crash the daemon, a bad or
stale file kept aside (never over an earlier one), and a directory probed for writing."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

log = logging.getLogger(__name__)


def atomic_write(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Write temp file, fsync, rename over `path`, fsync the directory: never a torn file.

    The file is created with `mode` (less what the umask removes): 0o600 keeps a secret
    unreadable to others from the first byte on. Raises OSError with `path` as it was before
    (`NotDurable` where even that could not be had)."""
    if not path.parent.is_dir():
        path.parent.mkdir(parents=True, exist_ok=True)
        fsync_dir(path.parent.parent)  # the new directory's own entry must survive too
    before = _before(path)
    _replace(path, data, mode)
    try:
        fsync_dir(path.parent)
    except OSError as exc:
        # The new file is in place but may not survive a power cut: a caller told "failed"
        # (a parameter: "nothing was changed") must find the older one there, not the new
        # one applying itself at the next start.
        _put_back(path, before, exc)
        raise


class NotDurable(OSError):
    """The new file is in place, its directory could not be synced and the older file could
    not be put back: what a power cut leaves is unknown, what is read now is the new file."""


@dataclass(frozen=True)
class _Before:
    """A file as it was before a write: its bytes and mode (None: there was none)."""

    data: bytes | None
    mode: int = 0o644


def _before(path: Path) -> _Before:
    """`path` as it is, to be put back; one that cannot be read counts as none (a load reads
    it as defaults too, and the rename replaces it anyway)."""
    try:
        with path.open("rb") as f:
            return _Before(f.read(), os.fstat(f.fileno()).st_mode & 0o7777)
    except OSError:
        return _Before(None)


def _put_back(path: Path, before: _Before, exc: OSError) -> None:
    """After a failed directory sync: `path` as it was before (NotDurable if that fails)."""
    try:
        if before.data is None:
            path.unlink(missing_ok=True)
        else:
            _replace(path, before.data, before.mode)
    except OSError as undo:
        raise NotDurable(
            exc.errno,
            f"{exc.strerror or exc}; the new {path.name} could not be taken back"
            f" ({undo.strerror or undo})",
        ) from exc
    with contextlib.suppress(OSError):
        fsync_dir(path.parent)  # the same sync that just failed: what it can, it does


def _replace(path: Path, data: bytes, mode: int) -> None:
    """`data` into a temp file beside `path`, synced, renamed over `path`."""
    tmp = _staged(path, data, mode)
    try:
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def _staged(path: Path, data: bytes, mode: int) -> Path:
    """`data` in a synced temp file beside `path` (its name returned), or the error and no
    temp file: a full disk or an interrupt must not leave a half-written one behind, and a
    failed removal (a read-only mount) must not hide why the write failed."""
    tmp = _temp_name(path, os.getpid(), threading.get_ident())
    created = False
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)  # less under a umask
        created = True
        try:
            write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        raise
    return tmp


class NewFile(NamedTuple):
    """One file of a set written together (`write_together`)."""

    path: Path
    data: bytes
    mode: int = 0o644


def write_together(files: Sequence[NewFile]) -> None:
    """Every file of `files`, or none changed: each is written and synced beside its path
    first, and only once all are they are renamed over their paths (a rename takes no room),
    then their directories synced. A full disk part of the way through leaves every file as it
    was (a set of logins half new would lock out the stations whose files are)."""
    staged: list[tuple[Path, Path]] = []
    try:
        for f in files:
            staged.append((_staged(f.path, f.data, f.mode), f.path))
    except BaseException:
        for tmp, _ in staged:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        raise
    for tmp, path in staged:
        os.replace(tmp, path)
    for directory in dict.fromkeys(path.parent for _, path in staged):
        fsync_dir(directory)


def write_all(fd: int, data: bytes) -> None:
    """All of `data`, or the error: a short write on a nearly full disk goes round again,
    and the next one raises ENOSPC."""
    view = memoryview(data)
    while view:
        written = os.write(fd, view)
        view = view[written:]


def fsync_dir(path: Path) -> None:
    dir_fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _temp_name(path: Path, pid: int, tid: int) -> Path:
    return path.with_name(f".{path.name}.{pid}.{tid}.tmp")


def remove_stale_temps(path: Path) -> list[Path]:
    """Delete temp files that writers of `path` left behind when they died mid-write."""
    removed = []
    for tmp in path.parent.glob(f".{path.name}.*.*.tmp"):
        pid_text = tmp.name[len(path.name) + 2 :].split(".", 1)[0]
        if not pid_text.isdigit() or _alive(int(pid_text)):
            continue
        try:
            tmp.unlink(missing_ok=True)
        except OSError as exc:  # a read-only mount: the file itself is whole, loading goes on
            log.warning("event=stale_temp_kept path=%s error=%r", tmp, exc.strerror or str(exc))
            continue
        removed.append(tmp)
    return removed


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process: not ours to judge
    return True


@dataclass(frozen=True)
class Loaded:
    """What a load found: the data (None = use defaults) and a warning if something was wrong."""

    data: dict[str, Any] | None
    warning: str | None = None
    kept_as: Path | None = None


def load_json(path: Path) -> Loaded:
    """Read a JSON object; a corrupt file is moved aside (`.corrupt-<time>`) and reported.

    Temp files left by writers that died mid-write are removed first (the file itself is whole).
    """
    if path.parent.is_dir():
        remove_stale_temps(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return Loaded(None)
    except OSError as exc:
        return Loaded(None, f"{path}: unreadable ({exc.strerror}); using defaults")
    try:
        data = json.loads(raw)
        if not isinstance(data, dict):
            raise ValueError(f"expected a JSON object, found {type(data).__name__}")
    except (ValueError, RecursionError) as exc:
        kept, where = set_aside(path)
        return Loaded(None, f"{path}: corrupt ({str(exc)[:120]}); {where}; using defaults", kept)
    return Loaded(data)


def keep_aside(path: Path, tag: str = "corrupt") -> Path:
    """Rename a file out of the way as `<name>.<tag>-<time>`, never over an earlier one."""
    stamp = time.strftime("%Y%m%dT%H%M%S")
    n = 0
    while True:
        kept = path.with_name(f"{path.name}.{tag}-{stamp}" + (f"-{n}" if n else ""))
        if not kept.exists():
            break
        n += 1
    os.replace(path, kept)
    return kept


def set_aside(path: Path) -> tuple[Path | None, str]:
    """`keep_aside` for a file found bad at a load, which must go on: where it went (None:
    it stays, a read-only mount) and that, said for a warning."""
    try:
        kept = keep_aside(path)
    except OSError as exc:
        return None, f"could not be kept aside ({exc.strerror or exc}), left in place"
    return kept, f"kept as {kept.name}"


def retire(path: Path) -> Path | None:
    """Move `path` aside as `<name>.stale-<time>` so it is never loaded again (None: no file)."""
    if not path.exists():
        return None
    stale = keep_aside(path, "stale")  # a rename needs no data blocks: it works on a full disk
    with contextlib.suppress(OSError):
        fsync_dir(path.parent)
    return stale


PROBE_BYTES = 64 * 1024
"""What the start-up probe writes: the room a save needs (a calibration or the parameters,
written beside the file it replaces, a few pages each), with margin. Six bytes once went
through on a disk that had filled while the daemon ran (its shutdown gave a page back), and
only the first save failed (issue 58, point 4)."""


def probe_writable(data_dir: Path) -> OSError | None:
    """None if a file of `PROBE_BYTES` can be created, written, synced and removed in
    `data_dir` (made if missing); otherwise the error. A read-only mount or a full disk fails
    here."""
    probe = data_dir / f".probe-{os.getpid()}"
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            write_all(fd, bytes(PROBE_BYTES))
            os.fsync(fd)
        finally:
            os.close(fd)
        probe.unlink()
    except OSError as exc:
        with contextlib.suppress(OSError):
            probe.unlink()
        return exc
    return None
