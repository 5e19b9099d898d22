"""The daemon's threads named for the OS, so `top -H`, `ps -L` and `/proc/<pid>/task/*/comm`
show which thread is which.

Python names its threads for itself only: the OS sees each new thread under its creator's name,
so every thread started from the main one read `python`, and a thread started from a Zenoh
callback read as Zenoh's own (`app-0`). `NamedThread` gives the OS the thread's name as it
starts (Linux keeps its first 15 bytes); `name_callback_threads` names the threads zenoh-python
starts for its callbacks. Both write the thread's `/proc/self/task/<tid>/comm`."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

OS_NAME_MAX = 15
"""Bytes of a thread name the Linux kernel keeps (16 with the terminating NUL)."""

CALLBACK_THREAD = "zenoh-callback"
"""The OS name of the threads zenoh-python runs its indirect callbacks on."""
CALLBACK_SUFFIX = "(pyo3-closure)"
"""How zenoh-python's callback threads are named in Python (`Thread-N (pyo3-closure)`)."""


class NamedThread(threading.Thread):
    """A `threading.Thread` that names itself for the OS (`os_name`) before its target runs."""

    def run(self) -> None:
        name_os_thread(self.name)
        super().run()


def os_name(name: str) -> bytes:
    """What the OS is given for `name`: UTF-8, cut to `OS_NAME_MAX` bytes on a character
    boundary."""
    data = name.encode()[:OS_NAME_MAX]
    return data.decode(errors="ignore").encode()


def name_os_thread(name: str) -> bool:
    """Name the calling thread for the OS; False where the OS cannot: the thread runs on
    unnamed, nothing else changes."""
    return _name(threading.get_native_id(), name)


def name_callback_threads() -> int:
    """Give `CALLBACK_THREAD` to each thread zenoh-python started for a callback declared with
    a plain function (one per queryable or subscriber; `cmd/**` and the reads run on Zenoh's
    own threads instead), which the OS saw under its creator's name. From the outside:
    zenoh-python starts them. How many were named."""
    return sum(
        _name(thread.native_id, CALLBACK_THREAD)
        for thread in threading.enumerate()
        if thread.native_id is not None and thread.name.endswith(CALLBACK_SUFFIX)
    )


def _name(tid: int, name: str) -> bool:
    """One thread of this process named for the OS (Linux: its `/proc/self/task/<tid>/comm`);
    False on another platform, or for a thread that has ended meanwhile."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        Path(f"/proc/self/task/{tid}/comm").write_bytes(os_name(name))
    except OSError:
        return False
    return True
