"""The event history counted for people: sessions, ride time, E-stops and faults over a range
(`rider events --summary`). One line per event: common/event_words.py."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable

from ride_machine.schema.base import OpenWireModel
from ride_machine.schema.event_kinds import EventKind
from ride_machine.schema.event_models import (
    CommandEvent,
    DaemonStartEvent,
    DroppedEvent,
    Event,
    FaultEvent,
    SessionEndedEvent,
)


class EventSummary(OpenWireModel):
    """What `rider events --summary` prints: counts over a time range of one machine's log."""

    machine_id: str
    since: float | None
    until: float | None
    events: int
    sessions_started: int
    sessions_done: int
    sessions_stopped: int
    sessions_faulted: int
    ride_time_s: float
    estops: int
    faults_by_code: dict[str, int]
    commands: int
    commands_refused: int
    daemon_starts: int
    unclean_stops: int
    dropped: int


def summarize(
    machine_id: str, events: Iterable[Event], since: float | None, until: float | None
) -> EventSummary:
    """Count sessions, ride time, E-stops and faults (by code) in `events`."""
    n = 0
    outcomes: Counter[str] = Counter()
    faults: Counter[str] = Counter()
    kinds: Counter[str] = Counter()
    ride = 0.0
    refused = dropped = unclean = 0
    for ev in events:
        n += 1
        kinds[ev.kind] += 1
        d = ev.details
        if isinstance(d, SessionEndedEvent):
            outcomes[d.outcome] += 1
            ride += d.duration_s
        elif isinstance(d, FaultEvent) and d.kind == "fault_raised":
            faults[d.code] += 1
        elif isinstance(d, CommandEvent) and not d.accepted:
            refused += 1
        elif isinstance(d, DroppedEvent):
            dropped += d.count
        elif isinstance(d, DaemonStartEvent) and d.previous_stop_clean is False:
            unclean += 1
    return EventSummary(
        machine_id=machine_id,
        since=since,
        until=until,
        events=n,
        sessions_started=kinds[EventKind.SESSION_STARTED],
        sessions_done=outcomes["DONE"],
        sessions_stopped=outcomes["STOPPED"] + outcomes["ABORTED"],
        sessions_faulted=outcomes["FAULT_HW"] + outcomes["FAULT_ESTOP"],
        ride_time_s=round(ride, 3),
        estops=kinds[EventKind.ESTOP_PRESSED],
        faults_by_code=dict(sorted(faults.items())),
        commands=kinds[EventKind.COMMAND],
        commands_refused=refused,
        daemon_starts=kinds[EventKind.DAEMON_START],
        unclean_stops=unclean,
        dropped=dropped,
    )
