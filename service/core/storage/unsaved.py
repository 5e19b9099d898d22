"""A calibration that could not be saved: tried again.

With the data dir read-only during `calibration set` (gain 40 -> 50), the save failed and so did
moving the older file aside; the dir writable again and the machine restarted, gain 40 was loaded as
current, with no warning. On a full disk the older file went aside, but nothing saved the new one
once there was room again. The store (service/core/storage/persist.py) now hands every calibration
it could not save here: it is written as soon as the directory takes it, every `RETRY_S` while the
machine runs and once more as it stops (`CalibrationStore.close`). What this cannot cover, the
refusal says.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from ride_machine.service.threads import NamedThread

log = logging.getLogger(__name__)

RETRY_S = 5.0
"""How often the calibration is tried again while the machine runs."""


class Unsaved:
    """The newest calibration not on disk (None: none), and the thread that tries it again."""

    def __init__(
        self,
        write: Callable[[bytes], None],
        submit: Callable[[Callable[[], None]], None] | None,
        on_saved: Callable[[], None],
    ) -> None:
        """`write` raises OSError when the disk refuses; `submit` runs a job on the store's
        writer (None: no retries while running, only at `close`)."""
        self._write = write
        self._submit = submit
        self._on_saved = on_saved
        self._data: bytes | None = None
        self._retrying = threading.Event()
        self._closed = threading.Event()

    @property
    def pending(self) -> bool:
        return self._data is not None

    def keep(self, data: bytes) -> None:
        """Save `data` later; tried again until saved, replaced (`drop`) or `stop`."""
        self._data = data
        if self._submit is None or self._retrying.is_set():
            return
        self._retrying.set()
        NamedThread(target=self._loop, name="calibration-retry", daemon=True).start()

    def drop(self) -> None:
        """A newer calibration is being saved: this one is no longer wanted."""
        self._data = None

    def _loop(self) -> None:
        while not self._closed.wait(RETRY_S) and self._data is not None:
            assert self._submit is not None
            self._submit(self.retry)
        self._retrying.clear()

    def retry(self) -> None:
        """One more try (on the store's writer thread)."""
        data = self._data
        if data is None:
            return
        try:
            self._write(data)
        except OSError:
            return
        if self._data is data:
            self._data = None
        self._on_saved()
        log.warning("event=calibration_saved_late")

    def stop(self) -> None:
        """No more tries on the thread (the store makes the last one as the machine stops)."""
        self._closed.set()
