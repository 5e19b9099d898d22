"""What the event log's tests share: a routine event, a started log, one page read back, and, for
the history process, its processes and a stop with one of them frozen."""

from __future__ import annotations

import contextlib
import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from bench.common import children
from ride_machine.schema.commands import Command, CommandRequest, Reply, ReplyCode
from ride_machine.schema.events import EventPage, EventQuery, SessionEndedEvent
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.eventdb import connect
from ride_machine.service.adapters.eventlog import EventLog
from ride_machine.service.adapters.eventread import read_page
from ride_machine.service.adapters.history import HistoryProcess
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.facts import CommandFacts

T0 = time.time()
"""Event times near now: retention prunes anything older than `max_age_days`."""
T0 = 1_800_000_000.0
"""A wall time for events written by hand (2027)."""
FLUSH_S = 30.0
"""A bound on a flush that must succeed: a history process that a loaded host starts slowly
(its Python and imports) writes its first batch seconds late; a quiet host, at once."""


def note(x: float) -> SessionEndedEvent:
    """A routine event that carries a number, `duration_s` (the safety record, calibrations and
    parameter writes among it, is kept apart: its own tests)."""
    return SessionEndedEvent(
        name="n",
        steps=1,
        steps_done=1,
        revolutions_done=0,
        revolutions_total=0,
        duration_s=x,
        outcome="DONE",
    )


def open_log(path: Path, kind: type[EventLog] = EventLog, **settings: object) -> EventLog:
    log = kind(path, "m1", EventsSection.model_validate(settings))
    log.start()
    return log


def page(log: EventLog, **criteria: object) -> EventPage:
    with connect(log.path) as conn:
        return read_page(conn, "m1", EventQuery(**criteria), log.settings.page_max)  # type: ignore[arg-type]


def facts(tid: str, *, repeat: bool = False) -> CommandFacts:
    """An accepted Home's facts, as the recorder keeps them for its event and log line."""
    request = CommandRequest(transaction_id=tid, timecode=T0, rider="r1")
    reply = Reply(
        transaction_id=tid,
        request_timecode=T0,
        command=Command.HOME.value,
        timecode=T0,
        success=True,
        code=ReplyCode.RESP_HOME_ACCEPTED,
        state=MachineState.HOMING,
    )
    return CommandFacts.of(Command.HOME, request, reply, None, repeat)


def command_tids(text: str) -> list[str]:
    """The transaction ids of the command log lines in `text`, in their order."""
    return [
        line.split(" tx=", 1)[1].split()[0] for line in text.splitlines() if "event=command" in line
    ]


def stored_kinds(path: Path) -> list[str]:
    """The kinds of the events in the log at `path`, in their order."""
    with connect(path) as conn:
        return [kind for (kind,) in conn.execute("SELECT kind FROM events ORDER BY seq")]


def history_processes() -> list[int]:
    """This process's children that run a history process."""
    found = []
    for pid in children(os.getpid()):
        with contextlib.suppress(OSError), open(f"/proc/{pid}/cmdline", "rb") as cmd:
            if b"service.adapters.history" in cmd.read():
                found.append(pid)
    return found


def closes_in_time(log: HistoryProcess, frozen: subprocess.Popen[bytes], others: set[int]) -> None:
    """`close` ends within its deadline (and a little: a spill), killing the frozen process and
    starting none in its place."""
    started = time.monotonic()
    log.close(timeout=1.0)
    assert time.monotonic() - started < 1.5
    assert frozen.poll() is not None  # killed
    assert set(history_processes()) - others == set()


@dataclass
class Counts:
    """The counters an `EventWriter` keeps up (`EventLog`'s), for a writer without its log."""

    written: int = 0
    lost: int = 0
    failures: int = 0
    last_error: str | None = None
