"""A file the daemon touches while its scan loop cycles, for a container healthcheck that reads
the file's age with `find` instead of opening a Zenoh session (docs/deploy.md, "The
healthcheck").

Only a path in `MACHINE_HEARTBEAT_FILE` turns it on (the image sets a tmpfs path). Once a
second a thread of its own looks at the loop's cycle counter and touches the file only when
the counter has moved: a stalled or frozen loop leaves the file to age. The file is removed
when the daemon stops, so a stopped daemon is unhealthy at the next check.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Callable, Mapping
from pathlib import Path

from ride_machine.service.threads import NamedThread

log = logging.getLogger("service.heartbeat")

HEARTBEAT_FILE_ENV = "MACHINE_HEARTBEAT_FILE"
INTERVAL_S = 1.0
"""How often the file is touched while the loop cycles; the check allows several missed."""


class HeartbeatFile:
    """Touches `path` every `interval_s` while `cycles()` keeps moving."""

    def __init__(
        self, path: Path, cycles: Callable[[], int], interval_s: float = INTERVAL_S
    ) -> None:
        self.path = path
        self.cycles = cycles
        self.interval_s = interval_s
        self.touched = 0
        self._failed = False
        self._last: int | None = None
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name="heartbeat", daemon=True)

    @classmethod
    def from_env(
        cls, cycles: Callable[[], int], env: Mapping[str, str] = os.environ
    ) -> HeartbeatFile | None:
        """The heartbeat file `MACHINE_HEARTBEAT_FILE` names, or None when it names none."""
        path = env.get(HEARTBEAT_FILE_ENV, "").strip()
        return cls(Path(path), cycles) if path else None

    def tick(self) -> bool:
        """Touch the file if the loop has cycled since the last tick; True if touched."""
        count = self.cycles()
        moved = self._last is not None and count != self._last
        self._last = count
        if not moved:
            return False
        try:
            self.path.touch()
        except OSError as exc:  # the check then fails: say why once, keep the daemon running
            if not self._failed:
                log.warning("event=heartbeat_file_failed path=%s error=%r", self.path, str(exc))
            self._failed = True
            return False
        self.touched += 1
        return True

    def start(self) -> None:
        log.info("event=heartbeat_file path=%s interval_s=%g", self.path, self.interval_s)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2 * self.interval_s)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.tick()
            self._stop.wait(self.interval_s)
