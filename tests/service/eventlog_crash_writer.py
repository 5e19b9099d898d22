"""The event-log crash test's child: forks writers that emit events as fast as a busy machine.

`go <first>` forks a writer that prints `pid <pid>`, then emits events first, first+1, ...
(`DaemonStopEvent(exit_code=i)`, about one per `PACE_S`) into an `EventLog` and prints `e <i>`
once event i is queued; the test SIGKILLs it, and this process prints `reaped <pid>`. Forking
from a process without threads keeps each kill cheap and safe.
"""

from __future__ import annotations

import os
import sys
import time
import traceback
from pathlib import Path

from schema.events import DaemonStopEvent
from service.config import EventsSection
from service.eventlog import EVENTS_FILE, EventLog

PACE_S = 0.0002
"""Seconds between events: thousands per second, far busier than a real ride."""
SETTINGS = EventsSection()


def _say(text: str) -> None:
    os.write(1, (text + "\n").encode())


def emit_forever(data_dir: Path, first: int, parent: int) -> None:
    log = EventLog(data_dir / EVENTS_FILE, "m1", SETTINGS)
    log.start()
    _say(f"pid {os.getpid()}")
    i = first
    while os.getppid() == parent:  # never outlive the server that forked us
        log.emit(DaemonStopEvent(reason="crash test", exit_code=i), time.time(), i)
        _say(f"e {i}")
        i += 1
        time.sleep(PACE_S)


def serve(data_dir: Path) -> None:
    _say("ready")
    for line in sys.stdin:
        word, _, arg = line.strip().partition(" ")
        if word != "go":
            return
        parent = os.getpid()
        pid = os.fork()
        if pid == 0:
            try:
                emit_forever(data_dir, int(arg), parent)
            except BaseException:
                traceback.print_exc()
                raise
            finally:
                os._exit(1)  # the writer only ends by a kill: anything else is a failure
        os.waitpid(pid, 0)
        _say(f"reaped {pid}")


if __name__ == "__main__":
    serve(Path(sys.argv[1]))
