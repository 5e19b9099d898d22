"""What the event log's tests share: a routine event, a started log, one page read back."""

from __future__ import annotations

import time
from pathlib import Path

from schema.events import EventPage, EventQuery, ParamEvent
from service.adapters.eventdb import connect
from service.adapters.eventlog import EventLog
from service.adapters.eventread import read_page
from service.config.model import EventsSection

T0 = time.time()
"""Event times near now: retention prunes anything older than `max_age_days`."""


def note(x: float) -> ParamEvent:
    """A routine event that carries a number (the safety record is kept apart: its own tests)."""
    return ParamEvent(name="tilt.tolerance_deg", old=x, new=x, persisted=False)


def open_log(path: Path, kind: type[EventLog] = EventLog, **settings: object) -> EventLog:
    log = kind(path, "m1", EventsSection.model_validate(settings))
    log.start()
    return log


def page(log: EventLog, **criteria: object) -> EventPage:
    with connect(log.path) as conn:
        return read_page(conn, "m1", EventQuery(**criteria), log.settings.page_max)  # type: ignore[arg-type]
