"""The event log's queue: what a full one drops and counts, and the room it keeps for the
safety record."""

from __future__ import annotations

from pathlib import Path

import pytest

from ride_machine.schema.events import DroppedEvent, EstopEvent, WatchdogEvent
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.writer_thread import SAFETY_RESERVE
from ride_machine.service.config.model import EventsSection
from tests.service.adapters.eventlog_support import FLUSH_S, T0, note, page


def stalled(tmp_path: Path, kind: type[EventLog], routine: int) -> EventLog:
    """A log of 16 places, not started (nothing drains it, as when the disk or the history
    process stalls), offered `routine` events."""
    log = kind(tmp_path / EVENTS_FILE, "m1", EventsSection(queue_capacity=16, batch_max=4))
    for i in range(routine):
        log.emit(note(float(i)), T0 + i, i)
    return log


def test_a_full_queue_drops_without_waiting_and_records_the_count_later(
    tmp_path: Path, kind: type[EventLog]
) -> None:
    log = stalled(tmp_path, kind, 20)
    assert (log.queued, log.dropped) == (16, 4)
    log.start()
    try:
        assert log.flush()
        events = page(log).events
        dropped = [e.details for e in events if isinstance(e.details, DroppedEvent)]
        assert dropped == [DroppedEvent(count=4)]
        assert len(events) == 17
        assert log.diag().dropped == 4
    finally:
        log.close()


@pytest.mark.hazard("H41")
def test_a_queue_full_of_routine_events_still_takes_the_safety_record(
    tmp_path: Path, kind: type[EventLog]
) -> None:
    log = stalled(tmp_path, kind, 40)  # a station's commands filling it
    estop = EstopEvent(kind="estop_pressed", reason="test")
    trip = WatchdogEvent(stalled_s=0.2)
    log.emit(estop, T0 + 50, 50)
    log.emit(trip, T0 + 51, 51)
    log.emit(note(99.0), T0 + 52, 52)  # routine: still dropped
    assert (log.queued, log.dropped) == (18, 25)
    for i in range(SAFETY_RESERVE):  # the reserve is bounded too
        log.emit(WatchdogEvent(stalled_s=float(i)), T0 + 60, 60)
    assert (log.queued, log.dropped) == (16 + SAFETY_RESERVE, 27)
    log.start()
    try:
        assert log.flush(FLUSH_S)
        details = [e.details for e in page(log, limit=400).events]
        at = details.index(estop)
        assert details[at - 16 : at + 2] == [*(note(float(i)) for i in range(16)), estop, trip]
        assert note(99.0) not in details
        assert DroppedEvent(count=27) in details
    finally:
        log.close()
