"""The event log's fixtures: one log, and the two writers (`kind`) every such test runs on."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.history import HistoryProcess
from tests.service.adapters.eventlog_support import open_log


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
