"""The event history for people: counts over a range (`rider events --summary`) and one line per
event (the CLI's and the UI's text)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable

from schema.base import OpenWireModel
from schema.departure import departure_text
from schema.event_models import (
    CalibrationEvent,
    ClockEvent,
    CommandEvent,
    CompletionEvent,
    DaemonStartEvent,
    DaemonStopEvent,
    Details,
    DroppedEvent,
    EstopEvent,
    Event,
    EventKind,
    FaultEvent,
    ParamEvent,
    RiderEvent,
    SessionEndedEvent,
    SessionStartedEvent,
    StateEvent,
    StorageEvent,
    WatchdogEvent,
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


def describe(details: Details) -> str:  # noqa: C901, PLR0911, PLR0912 - one branch per event kind
    """One human line for the details of an event (the CLI's and the UI's text)."""
    d = details
    if isinstance(d, dict):
        return " ".join(f"{k}={v}" for k, v in d.items() if k != "kind")
    if isinstance(d, CommandEvent):
        who = f" from {d.identity or d.rider}" if (d.identity or d.rider) else ""
        verdict = "accepted" if d.accepted else "refused"
        tail = f": {d.message}" if d.message and not d.accepted else ""
        again = " (repeat)" if d.repeat else ""
        return f"{d.command} tx={d.transaction_id}{who} {verdict} {d.code}{again}{tail}"
    if isinstance(d, CompletionEvent):
        return f"{d.command} tx={d.transaction_id} {d.outcome} -> {d.state} ({d.reason})"
    if isinstance(d, StateEvent):
        return f"{d.old} -> {d.new} ({d.reason})"
    if isinstance(d, FaultEvent):
        axis = f" axis={d.axis}" if d.axis else ""
        return f"{d.code}{axis}: {d.message}"
    if isinstance(d, EstopEvent):
        return f"state {d.state}" + (f" ({d.reason})" if d.reason else "")
    if isinstance(d, SessionStartedEvent):
        return f"{d.name!r} steps={d.steps} revolutions={d.revolutions_total} tx={d.transaction_id}"
    if isinstance(d, SessionEndedEvent):
        return (
            f"{d.name!r} {d.outcome} steps {d.steps_done}/{d.steps} revolutions"
            f" {d.revolutions_done}/{d.revolutions_total} in {d.duration_s:.1f} s"
        )
    if isinstance(d, CalibrationEvent):
        return f"{d.axis} {d.old} -> {d.new} persisted={d.persisted}"
    if isinstance(d, ParamEvent):
        what = "reset" if d.reset else "set"
        who = f" by {d.by}" if d.by else ""
        if not d.accepted:
            return f"{d.name} {what} {d.old!r} -> {d.new!r}{who} refused: {d.message}"
        return f"{d.name} {what} {d.old!r} -> {d.new!r}{who} persisted={d.persisted}"
    if isinstance(d, RiderEvent):
        if d.kind == "rider_lost" and d.mid_motion is not None:
            return departure_text(d.rider, d.policy, d.acted, d.mid_motion)
        return f"rider {d.rider}" + (f" policy={d.policy} acted={d.acted}" if d.policy else "")
    if isinstance(d, WatchdogEvent):
        return f"scan loop stalled {d.stalled_s * 1000:.0f} ms"
    if isinstance(d, ClockEvent):
        return f"host clock set {d.step_s:+.3f} s (wall times follow it from here)"
    if isinstance(d, DaemonStartEvent):
        clean = "" if d.previous_stop_clean is not False else " (previous run did not stop cleanly)"
        return f"pid {d.pid} hal={d.hal} period={d.period_s * 1000:g} ms{clean}"
    if isinstance(d, DaemonStopEvent):
        return f"{d.reason} exit={d.exit_code}"
    if isinstance(d, StorageEvent):
        return f"{d.what}: {d.error} (lost {d.lost})"
    return f"{d.count} events dropped (queue full)"
