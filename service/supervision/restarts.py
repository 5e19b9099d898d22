"""The child daemon as the supervisor keeps it: its record, what can happen to it (the
supervisor's events), how it ended in words, and the back-off before the next start."""

from __future__ import annotations

import signal
import subprocess
from dataclasses import dataclass
from enum import Enum

from service.supervision.outputguard import Stall


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
class Event:
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
