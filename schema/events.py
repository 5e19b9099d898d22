"""The machine's event history: one `Event` per thing that happened, read on `machine/<id>/events`.

Each event has a kind (`EventKind`) and typed details, one model per kind, told apart by their
`kind` field. A reader that meets a kind newer than itself keeps the details as a plain mapping
instead of failing, so old Riders can read a newer machine's history.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime
from enum import StrEnum
from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from schema.base import OpenWireModel
from schema.departure import departure_text
from schema.status import MachineState

ParamScalar = bool | int | float | str


class EventKind(StrEnum):
    """Every kind of event the machine records; the string is what the wire and the db carry."""

    COMMAND = "command"
    COMPLETION = "completion"
    STATE = "state"
    FAULT_RAISED = "fault_raised"
    FAULT_CLEARED = "fault_cleared"
    ESTOP_PRESSED = "estop_pressed"
    ESTOP_RELEASED = "estop_released"
    ESTOP_LATCHED = "estop_latched"
    ESTOP_RESET = "estop_reset"
    SESSION_STARTED = "session_started"
    SESSION_ENDED = "session_ended"
    CALIBRATION = "calibration"
    PARAM_CHANGED = "param_changed"
    SAFETY_CHANGED = "safety_changed"
    RIDER_LOST = "rider_lost"
    RIDER_RETURNED = "rider_returned"
    WATCHDOG_TRIP = "watchdog_trip"
    DAEMON_START = "daemon_start"
    DAEMON_STOP = "daemon_stop"
    STORAGE_FAILED = "storage_failed"
    EVENTS_DROPPED = "events_dropped"


class CommandEvent(OpenWireModel):
    """A command reached the scan loop: who sent it, and whether it was accepted."""

    kind: Literal["command"] = "command"
    command: str | None
    transaction_id: str | None = None
    rider: str | None = None
    """The sending Rider's Zenoh session id, when it named itself in the request."""
    identity: str | None = None
    """The authenticated user under the ACL profiles, when the bus can tell it."""
    accepted: bool
    code: str
    """The reply code when accepted (e.g. RESP_START_ACCEPTED), the error code when refused."""
    message: str = ""
    state: MachineState | None = None
    repeat: bool = False
    """A retry of a transaction already answered: the same reply again, nothing acted twice."""


class CompletionEvent(OpenWireModel):
    """A motion command ended: DONE, stopped, or a fault, with the transaction it ends."""

    kind: Literal["completion"] = "completion"
    command: str | None
    transaction_id: str | None = None
    outcome: str
    """As the completion notice says (schema/completion.py): DONE, STOPPED, FAULT_HW,
    FAULT_ESTOP, REFUSED, STORAGE_FAILED or ABORTED; see `code` and `reason`."""
    code: str | None = None
    state: MachineState
    reason: str = ""


class StateEvent(OpenWireModel):
    """A state transition with the reason the state machine gave."""

    kind: Literal["state"] = "state"
    old: MachineState
    new: MachineState
    reason: str = ""


class FaultEvent(OpenWireModel):
    """A fault raised, or the fault that was active cleared (by a new command or Stop)."""

    kind: Literal["fault_raised", "fault_cleared"]
    code: str
    message: str = ""
    axis: str | None = None


class EstopEvent(OpenWireModel):
    """The E-stop input pressed or released; the latch set, or reset by a command."""

    kind: Literal["estop_pressed", "estop_released", "estop_latched", "estop_reset"]
    state: MachineState | None = None
    reason: str = ""


class SessionStartedEvent(OpenWireModel):
    kind: Literal["session_started"] = "session_started"
    name: str
    steps: int
    revolutions_total: int
    transaction_id: str | None = None


class SessionEndedEvent(OpenWireModel):
    kind: Literal["session_ended"] = "session_ended"
    name: str
    steps: int
    steps_done: int
    revolutions_done: int
    revolutions_total: int
    duration_s: float
    outcome: str
    """As the Start's completion notice: DONE, STOPPED, FAULT_HW, FAULT_ESTOP, ABORTED."""


class CalibrationEvent(OpenWireModel):
    """An axis calibration changed (old → new values); `persisted` when written to data_dir."""

    kind: Literal["calibration"] = "calibration"
    axis: str
    old: dict[str, float | str | None] | None = None
    new: dict[str, float | str | None] | None = None
    """The axis's values, with `source` (measured / manual) and `at` (when)."""
    persisted: bool


class ParamEvent(OpenWireModel):
    """An online parameter written (or reset to its default) over the bus; a safety setting's
    write (service/core/safety.py) is a `safety_changed` event, refused ones included."""

    kind: Literal["param_changed", "safety_changed"] = "param_changed"
    name: str
    old: ParamScalar
    new: ParamScalar
    persisted: bool
    reset: bool = False
    transaction_id: str | None = None
    by: str | None = None
    """Who asked: the Rider id (`<login>/<zid>`) the write came with, as its sender said it."""
    accepted: bool = True
    """False: refused (`message` says why; `new` is what was asked), nothing changed."""
    message: str = ""


class RiderEvent(OpenWireModel):
    """The controlling Rider's liveliness token went away or came back."""

    kind: Literal["rider_lost", "rider_returned"]
    rider: str
    policy: str = ""
    acted: bool = False
    """On loss: the policy acted at once (False: no motion, or a grace period runs)."""
    mid_motion: bool | None = None
    """A motion was under way, paused or held by the E-stop when the Rider went (False: it
    left a machine at rest); None from a machine older than this field."""


class WatchdogEvent(OpenWireModel):
    kind: Literal["watchdog_trip"] = "watchdog_trip"
    stalled_s: float


class DaemonStartEvent(OpenWireModel):
    kind: Literal["daemon_start"] = "daemon_start"
    pid: int
    hal: str
    period_s: float
    previous_stop_clean: bool | None = None
    """False when the log's last run ended without a `daemon_stop` (killed or crashed)."""
    safety: dict[str, ParamScalar] | None = None
    """The safety settings this run started with (the config file's, or stricter persisted
    online values): the record of what the file set, beside `safety_changed` for the bus."""


class DaemonStopEvent(OpenWireModel):
    kind: Literal["daemon_stop"] = "daemon_stop"
    reason: str
    exit_code: int


class StorageEvent(OpenWireModel):
    """A write to data_dir failed (the event log itself, calibration, parameters)."""

    kind: Literal["storage_failed"] = "storage_failed"
    what: str
    error: str
    lost: int = 0
    """Events that could not be written because of it (for the event log)."""


class DroppedEvent(OpenWireModel):
    """Events the scan loop produced while the writer's queue was full (never written)."""

    kind: Literal["events_dropped"] = "events_dropped"
    count: int


KnownDetails = Annotated[
    CommandEvent
    | CompletionEvent
    | StateEvent
    | FaultEvent
    | EstopEvent
    | SessionStartedEvent
    | SessionEndedEvent
    | CalibrationEvent
    | ParamEvent
    | RiderEvent
    | WatchdogEvent
    | DaemonStartEvent
    | DaemonStopEvent
    | StorageEvent
    | DroppedEvent,
    Field(discriminator="kind"),
]
Details = Annotated[KnownDetails | dict[str, Any], Field(union_mode="left_to_right")]


class Event(OpenWireModel):
    """One row of the event log: `seq` only grows (never reused, even after pruning)."""

    seq: int
    time: float
    """Wall-clock seconds (Unix time)."""
    cycle: int | None = None
    """The scan cycle it happened in; None for events from outside the scan loop."""
    machine_id: str
    kind: str
    details: Details

    @model_validator(mode="after")
    def _kind_matches(self) -> Event:
        tag = self.details.get("kind") if isinstance(self.details, dict) else self.details.kind
        if tag != self.kind:
            raise ValueError(f"details are of kind {tag!r}, the event of kind {self.kind!r}")
        return self


class QueryError(ValueError):
    """A bad query parameter; `param` names it."""

    def __init__(self, param: str, message: str) -> None:
        super().__init__(message)
        self.param = param


@dataclass(frozen=True)
class EventQuery:
    """Which events to read: seq and time ranges (inclusive), kinds, and how many."""

    since: int | None = None
    until: int | None = None
    since_time: float | None = None
    until_time: float | None = None
    kinds: tuple[str, ...] = ()
    limit: int | None = None
    last: int | None = None
    """Only the newest `last` matching events (still oldest first in the page)."""

    @classmethod
    def from_params(cls, params: Mapping[str, str]) -> EventQuery:
        """From a selector's parameters: `since`, `until` (seq), `since_time`, `until_time`
        (Unix seconds), `kind` (comma-separated), `limit`, `last`."""
        known = {"since", "until", "since_time", "until_time", "kind", "limit", "last", "format"}
        for name in params:
            if name not in known:
                raise QueryError(name, f"unknown parameter {name!r}; known: {sorted(known)}")
        if params.get("format", "json").lower() not in ("json", "msgpack"):
            raise QueryError("format", f"format must be json or msgpack, got {params['format']!r}")
        kinds = tuple(k for k in params.get("kind", "").split(",") if k)
        valid = {k.value for k in EventKind}
        for kind in kinds:
            if kind not in valid:
                raise QueryError("kind", f"unknown event kind {kind!r}; known: {sorted(valid)}")
        return cls(
            since=_int(params, "since"),
            until=_int(params, "until"),
            since_time=_float(params, "since_time"),
            until_time=_float(params, "until_time"),
            kinds=kinds,
            limit=_int(params, "limit", minimum=1),
            last=_int(params, "last", minimum=1),
        )

    @classmethod
    def from_text(cls, text: str) -> EventQuery:
        """From a selector's parameter text; `;` (Zenoh's separator) and `&` both separate."""
        return cls.from_params(selector_params(text))

    def matches(self, event: Event) -> bool:
        """Whether `event` is one this query selects (ignoring `limit` and `last`)."""
        return (
            (self.since is None or event.seq >= self.since)
            and (self.until is None or event.seq <= self.until)
            and (self.since_time is None or event.time >= self.since_time)
            and (self.until_time is None or event.time <= self.until_time)
            and (not self.kinds or event.kind in self.kinds)
        )

    def params(self) -> str:
        """The selector parameters that ask for this query."""
        parts = []
        for name in ("since", "until", "since_time", "until_time", "limit", "last"):
            value = getattr(self, name)
            if value is not None:
                parts.append(f"{name}={value}")
        if self.kinds:
            parts.append("kind=" + ",".join(self.kinds))
        return ";".join(parts)


def selector_params(text: str) -> dict[str, str]:
    """A selector's parameters, split at `;` (Zenoh's separator) and at `&`."""
    params: dict[str, str] = {}
    for pair in re.split("[;&]", text):
        if pair:
            name, _, value = pair.partition("=")
            params[name] = value
    return params


MAX_INT = 2**63 - 1
"""The largest seq, limit or count a query may name (SQLite's INTEGER)."""


def _int(params: Mapping[str, str], name: str, minimum: int = 0) -> int | None:
    text = params.get(name)
    if text is None or text == "":
        return None
    try:
        value = int(text)
    except ValueError:
        raise QueryError(name, f"{name} must be an integer, got {text!r}") from None
    if value < minimum:
        raise QueryError(name, f"{name} must be at least {minimum}, got {value}")
    if value > MAX_INT:
        raise QueryError(name, f"{name} must be at most {MAX_INT}, got {value}")
    return value


def _float(params: Mapping[str, str], name: str) -> float | None:
    text = params.get(name)
    if text is None or text == "":
        return None
    try:
        value = float(text)
    except ValueError:
        raise QueryError(name, f"{name} must be Unix seconds, got {text!r}") from None
    if math.isnan(value):
        raise QueryError(name, f"{name} must be Unix seconds, got {text!r}")
    return value


class EventPage(OpenWireModel):
    """One reply of the `events` queryable; ask again from `next_since` while `more`."""

    machine_id: str
    events: list[Event]
    more: bool
    next_since: int | None = None
    first_seq: int | None = None
    """The oldest seq still kept (older ones were pruned by retention)."""
    last_seq: int | None = None


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


AGE_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0, "w": 7 * 86400.0}


def parse_point(text: str, now: float) -> tuple[int | None, float | None]:
    """`--since`/`--until`: (seq, None) for a number, (None, Unix time) for an age or a time."""
    text = text.strip()
    if text.isascii() and text.isdigit():
        if int(text) > MAX_INT:
            raise ValueError(f"{text!r} is past the largest seq number ({MAX_INT})")
        return int(text), None
    unit = AGE_UNITS.get(text[-1:].lower())
    if unit is not None:
        try:
            return None, now - float(text[:-1]) * unit
        except ValueError:
            pass
    try:
        return None, datetime.fromisoformat(text).timestamp()
    except ValueError:
        raise ValueError(
            f"{text!r} is neither a seq number, an age (30m, 12h, 7d) nor a time (2026-11-27T14:00)"
        ) from None


def query_of(
    since: str | None,
    until: str | None,
    kinds: Iterable[str],
    now: float,
    last: int | None = None,
) -> EventQuery:
    """A query from command-line words: `--since`/`--until` (see `parse_point`) and `--kind`
    (repeatable, comma-separated); ValueError says what is wrong."""
    s_seq, s_time = parse_point(since, now) if since else (None, None)
    u_seq, u_time = parse_point(until, now) if until else (None, None)
    wanted = tuple(k for arg in kinds for k in arg.split(",") if k)
    known = {k.value for k in EventKind}
    for kind in wanted:
        if kind not in known:
            raise ValueError(f"unknown event kind {kind!r}; known: {', '.join(sorted(known))}")
    return EventQuery(
        since=s_seq, until=u_seq, since_time=s_time, until_time=u_time, kinds=wanted, last=last
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
    if isinstance(d, DaemonStartEvent):
        clean = "" if d.previous_stop_clean is not False else " (previous run did not stop cleanly)"
        return f"pid {d.pid} hal={d.hal} period={d.period_s * 1000:g} ms{clean}"
    if isinstance(d, DaemonStopEvent):
        return f"{d.reason} exit={d.exit_code}"
    if isinstance(d, StorageEvent):
        return f"{d.what}: {d.error} (lost {d.lost})"
    return f"{d.count} events dropped (queue full)"
