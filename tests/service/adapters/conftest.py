"""The event log's fixtures: one log, and the two writers (`kind`) every such test runs on."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.eventwriter import EventWriter
from ride_machine.service.adapters.history import HistoryProcess
from ride_machine.service.config.model import EventsSection
from tests.service.adapters.eventlog_support import T0, Counts, open_log


@pytest.fixture
def log(tmp_path: Path) -> Iterator[EventLog]:
    events = open_log(tmp_path / EVENTS_FILE)
    yield events
    events.close()


@pytest.fixture(params=[EventLog, HistoryProcess], ids=["thread", "process"])
def kind(request: pytest.FixtureRequest) -> type[EventLog]:
    return request.param  # type: ignore[no-any-return]


@pytest.fixture
def any_log(tmp_path: Path, kind: type[EventLog]) -> Iterator[EventLog]:
    events = open_log(tmp_path / EVENTS_FILE, kind)
    yield events
    events.close()


@pytest.fixture
def writer(tmp_path: Path) -> Iterator[EventWriter]:
    """A log's writer without its thread, its log open: each write is the test's own."""
    events = EventWriter(Counts(), tmp_path / EVENTS_FILE, "m1", EventsSection(), None)
    events.claim(0.1)
    events.open_or_replace(T0)
    yield events
    events.release()
