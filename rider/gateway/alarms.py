"""Which of a machine's events become OPC UA events, with what severity and message (pure).

OPC UA severities run from 1 to 1000; SCADA alarm lists band them (commonly 1-200 low, 201-500
medium, 501-800 high, 801-1000 urgent). Events the plant does not need on an alarm list
(commands, parameter writes, calibrations) stay in the machine's history only.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from ride_machine.schema.events import (
    CompletionEvent,
    EstopEvent,
    Event,
    FaultEvent,
    RiderEvent,
    SessionEndedEvent,
    StorageEvent,
    WatchdogEvent,
)


class Severity(IntEnum):
    """The bands the gateway uses."""

    INFO = 100
    NOTICE = 300
    WARNING = 500
    HIGH = 700
    URGENT = 900


@dataclass(frozen=True)
class Alarm:
    """One OPC UA event to fire on the machine's object."""

    kind: str
    severity: Severity
    message: str
    code: str = ""


def alarm_of(event: Event) -> Alarm | None:
    """The OPC UA event for a machine event, or None for a kind that is not forwarded."""
    d = event.details
    kind = event.kind
    if isinstance(d, FaultEvent):
        if kind == "fault_raised":
            return Alarm(kind, Severity.HIGH, f"fault {d.code}: {d.message}", d.code)
        return Alarm(kind, Severity.NOTICE, f"fault {d.code} cleared", d.code)
    if isinstance(d, EstopEvent):
        if kind == "estop_pressed":
            return Alarm(kind, Severity.URGENT, "E-stop pressed", "ESTOP")
        if kind == "estop_released":
            return Alarm(kind, Severity.NOTICE, "E-stop released (still latched)", "ESTOP")
        return None  # latched / reset: the pressed and released events say it
    if isinstance(d, SessionEndedEvent):
        severity = Severity.INFO if d.outcome == "DONE" else Severity.WARNING
        text = f"session {d.name!r} ended {d.outcome}: steps {d.steps_done}/{d.steps}"
        return Alarm(kind, severity, text, d.outcome)
    if isinstance(d, CompletionEvent) and d.command != "Start":
        if d.outcome == "DONE":
            return None  # a homing or calibration that did its job: the state says it
        text = f"{d.command} ended {d.outcome}: {d.reason}"
        return Alarm(kind, Severity.WARNING, text, d.code or d.outcome)
    if isinstance(d, RiderEvent) and kind == "rider_lost" and d.acted:
        return Alarm(kind, Severity.HIGH, f"controlling Rider lost: policy {d.policy}", "RIDER")
    if isinstance(d, WatchdogEvent):
        return Alarm(kind, Severity.URGENT, f"scan loop stalled {d.stalled_s:.3f} s", "WATCHDOG")
    if isinstance(d, StorageEvent):
        text = f"cannot write {d.what}: {d.error}"
        return Alarm(kind, Severity.HIGH, text, "STORAGE_FAILED")
    return None
