"""The child daemon as the supervisor keeps it: the restart policy and bounds, its record, what
can happen to it (the supervisor's events), how it ended in words, and the back-off before the
next start."""

from __future__ import annotations

import signal
import subprocess
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from .outputguard import Stall


@dataclass(frozen=True)
class SupervisorOptions:
    """Restart policy and bounds."""

    backoff_s: float = 0.5
    """The wait before the first restart; each one after waits twice the one before."""
    backoff_max_s: float = 8.0
    """The longest wait before a restart."""
    stable_s: float = 10.0
    """A child up this long resets the back-off to `backoff_s`."""
    hang_s: float | None = None
    """A daemon whose scan has completed no cycle for this long is killed and restarted,
    whatever its outputs (they were made safe at the watchdog limit if any was on); None:
    `HANG_S` (supervisor.py), or three watchdog limits when that is longer."""
    start_timeout_s: float = 30.0
    """A child whose liveliness token has not appeared by then is killed and restarted."""
    exit_grace_s: float = 1.0
    """After the token goes: how long a child that is still running may take to exit."""
    stop_timeout_s: float = 10.0
    """How long a child may take to end once signalled (a SIGTERM to stop, a SIGKILL when hung)."""
    world_period_s: float = 0.005
    """With the simulator: how often the plant steps its world (`sim.plant`)."""
    plant_dir: Path | None = None
    """With the simulator: attach to a plant already running there (`--plant`, a compose
    service of its own) instead of starting one as a child."""
    log_level: str = "info"
    """The child daemon's `--log-level`."""


class Backoff:
    """0.5 s, 1 s, 2 s, … up to a maximum; back to the start after a stable run."""

    def __init__(self, first_s: float, most_s: float) -> None:
        self.first = first_s
        self.most = most_s
        self._next = first_s

    def delay(self, lived_s: float | None, stable_s: float) -> float:
        """The wait before the next start, after a child that lived `lived_s`."""
        if lived_s is not None and lived_s >= stable_s:
            self._next = self.first
        delay = self._next
        self._next = min(self._next * 2, self.most)
        return delay


class Kind(Enum):
    """What the supervisor's loop hears of: the child exited, came or went on the bus, hung;
    or a signal asked it to stop."""

    EXITED = "exited"
    PRESENCE = "presence"
    HUNG = "hung"
    STOP = "stop"


@dataclass(frozen=True)
class Happening:
    """One thing for the supervisor's loop, queued from the thread that saw it."""

    kind: Kind
    generation: int = 0
    code: int = 0
    present: bool = False
    stall: Stall | None = None


@dataclass
class Child:
    """One start of the daemon: its process, which start it is, and since when it is up."""

    proc: subprocess.Popen[bytes]
    generation: int
    started: float
    up_since: float | None = None
    down: bool = False


def describe_exit(code: int) -> str:
    """How the daemon ended, in words, from its exit code (negative: the signal)."""
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"the daemon was killed by {name}"
    if code == 0:
        return "the daemon exited (code 0) without being asked to"
    return f"the daemon exited with code {code}"
