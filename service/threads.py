"""The daemon's threads named for the OS, so `top -H`, `ps -L` and `/proc/<pid>/task/*/comm`
show which thread is which.

Python names its threads for itself only: the OS sees each new thread under its creator's name,
so every thread started from the main one read `python`, and a thread started from a Zenoh
callback read as Zenoh's own (`app-0`). `NamedThread` gives the OS the thread's name as it
starts (Linux keeps its first 15 bytes), by its `comm` file in /proc; `name_callback_threads`
names the threads zenoh-python starts for its callbacks, from the outside, by theirs. `prctl` is
the process's one call of the Linux `prctl(2)` (timer slack and the parent's death signal in
service/core/scan/tuning.py), through `libc`, its one handle on the C library (`sched_setattr(2)`
there too); both load `ctypes` at their first use, so a process that only names its threads
(the event history's) never does (~0.4 MiB, bench.rss_soak)."""

from __future__ import annotations

import contextlib
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import ctypes

OS_NAME_MAX = 15
"""Bytes of a thread name the Linux kernel keeps (16 with the terminating NUL)."""

CALLBACK_THREAD = "zenoh-callback"
"""The OS name of the threads zenoh-python runs its indirect callbacks on."""
CALLBACK_SUFFIX = "(pyo3-closure)"
"""How zenoh-python's callback threads are named in Python (`Thread-N (pyo3-closure)`)."""

_libc: ctypes.CDLL | None = None


class NamedThread(threading.Thread):
    """A `threading.Thread` that names itself for the OS (`os_name`) before its target runs."""

    def run(self) -> None:
        name_os_thread(self.name)
        super().run()


class TimedThread:
    """A named daemon thread (`_run`, in a subclass) that sleeps only through `sleep`, which
    `stop()` cuts short: a timed acquire of a lock held until `stop()`, one raw lock per
    wake-up where `Event.wait` builds a `Condition` waiter each time (bench.cost)."""

    def __init__(self, name: str) -> None:
        self._name = name
        self._gate = threading.Lock()
        self._gate.acquire()  # held until `stop()`
        self._stopped = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = NamedThread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Wake the thread to end, and wait for it (a bounded wait)."""
        if not self._stopped:
            self._stopped = True
            self._gate.release()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def sleep(self, seconds: float) -> bool:
        """Sleep up to `seconds`; False, at once, once `stop()` was called."""
        return not self._stopped and not self._gate.acquire(True, seconds)

    def _run(self) -> None:
        raise NotImplementedError


def os_name(name: str) -> bytes:
    """What the OS is given for `name`: UTF-8, cut to `OS_NAME_MAX` bytes on a character
    boundary."""
    data = name.encode()[:OS_NAME_MAX]
    return data.decode(errors="ignore").encode()


def name_os_thread(name: str) -> bool:
    """Name the calling thread for the OS (its `/proc/thread-self/comm`, what `prctl(PR_SET_NAME)`
    sets); False where the OS cannot: the thread runs on unnamed, nothing else changes."""
    return sys.platform.startswith("linux") and _write_comm(Path("/proc/thread-self/comm"), name)


def _write_comm(comm: Path, name: str) -> bool:
    """`name` into a thread's `comm` file in /proc; False where it cannot be written (no such
    thread any more, no /proc)."""
    try:
        comm.write_bytes(os_name(name))
    except OSError:
        return False
    return True


def libc() -> ctypes.CDLL | None:
    """The process's C library (Linux), loaded at first use, errno kept for
    `ctypes.get_errno()`; None elsewhere or where it cannot be loaded."""
    global _libc  # noqa: PLW0603 - one handle on the C library, loaded at first use
    if not sys.platform.startswith("linux"):
        return None
    if _libc is None:
        import ctypes  # at first use: see the module's docstring

        with contextlib.suppress(OSError):
            _libc = ctypes.CDLL(None, use_errno=True)
    return _libc


def prctl(option: int, arg: int | bytes) -> bool:
    """Linux `prctl(2)` on the calling thread or process, `arg` a number or a string; False
    where it is not available or refused (`ctypes.get_errno()` then says why)."""
    lib = libc()
    if lib is None:
        return False
    import ctypes  # loaded by `libc` already

    try:
        value = ctypes.c_char_p(arg) if isinstance(arg, bytes) else ctypes.c_ulong(arg)
        return int(lib.prctl(option, value, 0, 0, 0)) == 0
    except AttributeError:
        return False


def name_callback_threads() -> int:
    """Give `CALLBACK_THREAD` to each thread zenoh-python started for a callback declared with
    a plain function (one per queryable or subscriber; `cmd/**` and the reads run on Zenoh's
    own threads instead), which the OS saw under its creator's name. From the outside, by
    `/proc/self/task/<tid>/comm`: zenoh-python starts them. How many were named."""
    if not sys.platform.startswith("linux"):
        return 0
    named = 0
    for thread in threading.enumerate():
        tid = thread.native_id
        if tid is None or not thread.name.endswith(CALLBACK_SUFFIX):
            continue
        named += _write_comm(Path(f"/proc/self/task/{tid}/comm"), CALLBACK_THREAD)  # or ended
    return named
