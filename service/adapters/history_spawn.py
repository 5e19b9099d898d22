"""How and when the daemon starts its history process: the command (`python -m
ride_machine.service.adapters.history_writer` on the daemon's own interpreter, with this tree on
its path and the daemon's log level), and the pause before a new one (`Pause`: plain logic, the
time an argument)."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

RESPAWN_S = 1.0
"""A history process that ended is started again after this long; one that keeps ending
within `STEADY_S` of its start waits twice as long each time, up to `RESPAWN_MAX_S`."""
RESPAWN_MAX_S = 30.0
STEADY_S = 10.0
PYTHON = sys.executable
"""The interpreter the history process runs on: the daemon's own."""


def start_writer(path: Path, machine_id: str, settings_json: str) -> subprocess.Popen[bytes]:
    """The history process of the log at `path`, its stdin and stdout piped to the daemon;
    OSError when it cannot start (out of memory or of processes)."""
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    level = logging.getLevelName(logging.getLogger().getEffectiveLevel()).lower()
    module = "ride_machine.service.adapters.history_writer"
    return subprocess.Popen(
        [PYTHON, "-m", module, str(path), machine_id, settings_json, level],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        bufsize=0,
        env=env,
    )


class Pause:
    """The wait before the next process: `RESPAWN_S` after one that lived `STEADY_S`, twice the
    last after one that did not, or could not start, up to `RESPAWN_MAX_S`."""

    def __init__(self) -> None:
        self.started_at = float("-inf")
        self.seconds = RESPAWN_S

    def started(self, now: float) -> None:
        self.started_at = now

    def failed(self) -> None:
        """It could not start: tried again, less often."""
        self.seconds = min(RESPAWN_MAX_S, self.seconds * 2)

    def ended(self, now: float) -> None:
        if now - self.started_at >= STEADY_S:
            self.seconds = RESPAWN_S
        else:
            self.failed()

    def left(self, now: float) -> float:
        """How long until the next may start."""
        return self.started_at + self.seconds - now
