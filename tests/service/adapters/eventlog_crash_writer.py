"""The event-log crash test's child: forks writers that emit events as fast as a busy machine.

It is the persistence crash test's server (`persist_crash_writer.serve`) with another writer:
`go <first>` forks a writer that prints `pid <pid>`, then emits events first, first+1, ...
(`DaemonStopEvent(exit_code=i)`, about one per `PACE_S`) into an `EventLog` and prints `e <i>`
once event i is queued; the test SIGKILLs it, and this process prints `reaped <pid>`. Forking
from a process without threads keeps each kill cheap and safe.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from ride_machine.schema.events import DaemonStopEvent
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.config.model import EventsSection
from tests.service.core.storage.persist_crash_writer import _say, serve

PACE_S = 0.0002
"""Seconds between events: thousands per second, far busier than a real ride."""
SETTINGS = EventsSection()


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


if __name__ == "__main__":
    serve(Path(sys.argv[1]), emit_forever)
