"""The OPC UA standard address space (about 6,000 nodes) read from a file on demand, not held in
memory: asyncua's `Server.init` builds every standard node as Python objects (about 50 MB of the
gateway's RSS, and 2.4 s of its start); with a shelf of them (asyncua's `load_aspace_shelf`) a
node is read from disk the first time a service touches it, and only those stay in memory.

The shelf is made once per asyncua and Python version, by a child process (building it needs
the whole space in memory, which the serving process should never have held), in the cache
directory (`--cache-dir`; by default `$XDG_CACHE_HOME/ride-machine` or `~/.cache/ride-machine`,
else `<tmp>/ride-machine-<uid>`, for a container with a read-only root and a tmpfs /tmp), under a
lock, and named `ready` only once complete. Without a usable cache directory the gateway builds
the space in memory as before (and says so).

A shelf is pickles, and loading a pickle runs what it says: the gateway uses one only from a
directory of its own (made 0700, owned by its user, writable by nobody else).
"""

from __future__ import annotations

import asyncio
import fcntl
import logging
import os
import stat
import subprocess
import sys
import tempfile
from importlib import metadata
from pathlib import Path

from asyncua.server.internal_server import InternalServer

log = logging.getLogger(__name__)

BUILD_TIMEOUT_S = 120.0
"""A child that builds the shelf: ~3 s of CPU on a quiet host; bounded for a loaded one."""


def default_dirs() -> tuple[Path, ...]:
    """Where to keep the cache unless told: the user's cache, else a directory of the temp
    directory's (a read-only root with a tmpfs /tmp)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ride-machine", Path(tempfile.gettempdir()) / f"ride-machine-{os.getuid()}"


def first(cache_dirs: tuple[Path, ...]) -> Path | None:
    """The shelf in the first of `cache_dirs` that has or can make one."""
    for cache_dir in cache_dirs:
        if (shelf := ensure(cache_dir)) is not None:
            return shelf
    return None


class Unsafe(OSError):
    """A cache directory someone else owns or may write."""


def _own(directory: Path) -> None:
    """`directory`, made private if new; `Unsafe` unless ours alone."""
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = directory.lstat()
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.geteuid() or st.st_mode & 0o022:
        raise Unsafe(f"{directory} is not a directory of this user's alone")


def shelf_path(cache_dir: Path) -> Path:
    """The shelf for this asyncua and this Python (pickles of its objects)."""
    version = metadata.version("asyncua")
    py = f"{sys.version_info.major}{sys.version_info.minor}"
    return cache_dir / f"opcua-nodeset-asyncua{version}-py{py}" / "nodes"


def _ready(shelf: Path) -> Path:
    return shelf.parent / "ready"


def ensure(cache_dir: Path) -> Path | None:
    """The shelf, made first if it is not there; None if it cannot be (said in the log)."""
    shelf = shelf_path(cache_dir)
    try:
        _own(shelf.parent.parent)
        _own(shelf.parent)
        if _ready(shelf).exists():
            return shelf
        done = subprocess.run(
            [sys.executable, "-m", "ride_machine.rider.gateway.nodeset_cache", str(shelf)],
            capture_output=True,
            text=True,
            timeout=BUILD_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        log.warning("event=nodeset_cache_unavailable dir=%s error=%s", cache_dir, exc)
        return None
    if done.returncode != 0 or not _ready(shelf).exists():
        tail = done.stderr.strip().splitlines()[-1:] or ["no output"]
        log.warning("event=nodeset_cache_unavailable dir=%s error=%s", cache_dir, tail[0])
        return None
    return shelf


def load(iserver: InternalServer, shelf: Path) -> None:
    """The standard nodes from `shelf`, read as they are touched."""
    iserver.aspace.load_aspace_shelf(shelf)


def build(shelf: Path) -> None:
    """Make the shelf (in this process: it holds the whole space meanwhile), under a lock, in a
    directory of its own, then mark it ready."""
    _own(shelf.parent)
    with (shelf.parent / "lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if _ready(shelf).exists():
            return  # another gateway made it meanwhile
        with tempfile.TemporaryDirectory(dir=shelf.parent) as tmp:
            made = Path(tmp) / shelf.name
            asyncio.run(_fill(made))
            for part in Path(tmp).iterdir():  # one file or several, as the dbm backend has it
                os.replace(part, shelf.parent / part.name)
        _ready(shelf).write_text("complete\n")


async def _fill(path: Path) -> None:
    """asyncua fills the standard space, then writes it to a shelf at `path` (it is not there)."""
    await InternalServer().load_standard_address_space(path)


if __name__ == "__main__":
    build(Path(sys.argv[1]))
