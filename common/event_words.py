"""One line for people per event: the text `rider events`, the UI's Events panel and the export's
`text` column all print (docs/events.md, "How an event reads").

One text function per event kind (`TEXTS`), so a kind added to the schema without its text fails
at import and in tests/common/test_event_text.py. The rules they share:

- numbers rounded to what the instrument resolves, with their unit (`QUANTITIES`; a parameter's
  unit comes from its name, `param_value`): `revolution 4.000 s`, `home arc 9.9°`;
- durations as durations (`250 ms`, `12.3 s`, `3 min 05 s`), times as local times
  (`2026-12-04 10:22:19`);
- a Rider named by its login and a short id (`rider_name`: `bay1 · 9d617a`), never the whole
  32-digit session id;
- no Python in sight: no dict, no repr, no `None`, `True` or `key=value`.

The raw record stays as it was: `rider events --json`, `machine events export`, the queryable.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from datetime import datetime
from typing import Any

from ride_machine.schema.event_kinds import EventKind
from ride_machine.schema.event_models import (
    CalibrationEvent,
    ClockEvent,
    CommandEvent,
    CompletionEvent,
    DaemonStartEvent,
    DaemonStopEvent,
    Details,
    DroppedEvent,
    EstopEvent,
    FaultEvent,
    ParamEvent,
    RiderEvent,
    SessionEndedEvent,
    SessionStartedEvent,
    StateEvent,
    StorageEvent,
    WatchdogEvent,
)

from .departure import departure_text

SHORT_ID = 6
"""Hex digits of a Rider's session id shown beside its login: 16.7 million to tell apart."""


def rider_name(rider: str | None, identity: str | None = None) -> str:
    """Who a Rider is, for people: its login (station) and a short session id, `bay1 · 9d617a`.

    The one place event text names a Rider (commands, parameter writes, departures). `rider` is
    the Rider id the event carries (`<login>/<zid>`, or schema 1's bare `<zid>`), `identity` the
    same once the machine could confirm it (then it is the one named). Empty when the event
    names nobody."""
    named = identity or rider
    if not named:
        return ""
    login, slash, zid = named.partition("/")
    if not slash:  # schema 1: the session id alone
        login, zid = "", login
    return " · ".join(part for part in (login, zid[:SHORT_ID]) if part)


def asker(rider: str | None, identity: str | None, operator: str | None = None) -> str:
    """Who asked for a command or a write: `rider_name`, marked `(claimed)` when the Rider it
    names never confirmed that it sent it (a Pause, Stop or check is not asked; a record older
    than confirmations; a Rider that did not answer): the sender's word, not proof. With the
    person the Rider acted for (the gateway's OPC UA user): `gateway · 4f2a1c for jane`."""
    name = rider_name(rider, identity)
    if name and not identity:
        return f"{name} (claimed)"
    return f"{name} for {operator}" if name and operator else name


# ----------------------------------------------------------------------------------- numbers
def fixed(value: float, decimals: int) -> str:
    """`value` with exactly `decimals` decimals (never `-0.0`)."""
    text = f"{value:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text


def trimmed(value: float, decimals: int) -> str:
    """`value` to at most `decimals` decimals, without trailing zeros: 45.0 → 45, 0.25 → 0.25."""
    text = fixed(value, decimals)
    return text.rstrip("0").rstrip(".") if "." in text else text


def number(value: float) -> str:
    """A number whose resolution nothing tells: six significant digits at most."""
    if isinstance(value, int) or not math.isfinite(value):
        return str(value)
    return f"{value:.6g}"


def with_unit(text: str, unit: str) -> str:
    """`9.9°`, `4.000 s`: degree signs stick to the number, other units take a space."""
    if not unit:
        return text
    return f"{text}{unit}" if unit.startswith("°") else f"{text} {unit}"


QUANTITIES: dict[str, tuple[str, str, int]] = {
    "offset_counts": ("offset", "counts", 1),
    "gain_counts_per_deg": ("gain", "counts/°", 3),
    "revolution_s": ("revolution", "s", 3),
    "home_arc_deg": ("home arc", "°", 1),
    "speed_dps": ("speed", "°/s", 1),
}
"""A calibration's values: (the word, the unit, the decimals the measurement resolves). The
tilt's analog input reads whole counts (an offset averages several: a tenth), its gain to a
thousandth of a count per degree; the revolution is timed by a 10 ms scan, shown to 1 ms as
`rider calibration` does; the home arc to a tenth of a degree."""

PARAM_UNITS: tuple[tuple[str, str, int], ...] = (
    ("_dps", "°/s", 1),
    ("_deg", "°", 2),
    ("_s", "s", 3),
)
"""A parameter's unit and decimals by the end of its name (`tilt.max_deg`, `bus.heartbeat_s`):
the same units as the parameter table (service/core/storage/params.py, checked by the test)."""


def param_unit(name: str) -> tuple[str, int | None]:
    """The unit and decimals of parameter `name`; no unit and None for a plain number."""
    for suffix, unit, decimals in PARAM_UNITS:
        if name.endswith(suffix):
            return unit, decimals
    return "", None


def param_value(name: str, value: bool | int | float | str) -> str:
    """A parameter's value as people write it: `50°`, `0.25 s`, `pause`, `on`."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, str):
        return value
    unit, decimals = param_unit(name)
    if isinstance(value, int) or decimals is None:
        return with_unit(number(value), unit)
    return with_unit(trimmed(value, decimals), unit)


def duration(seconds: float) -> str:
    """A span of time: `250 ms`, `12.3 s`, `3 min 05 s`, `2 h 04 min`, `3 d 04 h`."""
    s = abs(seconds)
    if s < 1:
        return f"{s * 1000:.0f} ms"
    if s < 60:
        return f"{s:.1f} s"
    minutes, sec = divmod(round(s), 60)
    if minutes < 60:
        return f"{minutes} min {sec:02d} s"
    hours, minutes = divmod(minutes, 60)
    if hours < 24:
        return f"{hours} h {minutes:02d} min"
    days, hours = divmod(hours, 24)
    return f"{days} d {hours:02d} h"


def local_time(seconds: float) -> str:
    """A wall time (Unix seconds) in local time, to the second: `2026-12-04 10:22:19`."""
    return datetime.fromtimestamp(seconds).strftime("%Y-%m-%d %H:%M:%S")


def words(name: str | None) -> str:
    """A command's name in words: `CalibrateTilt` → `Calibrate tilt`."""
    if not name:
        return "a command"
    out = name[0] + "".join(f" {c.lower()}" if c.isupper() else c for c in name[1:])
    return out


def tx(transaction_id: str | None) -> str:
    """The transaction an event belongs to, last on its line: ` [tx 2a671776-1]`."""
    return f" [tx {transaction_id}]" if transaction_id else ""


# ----------------------------------------------------------------------------- one per kind
def command_text(d: CommandEvent) -> str:
    """`Start accepted from bay1 · 9d617a, now RUNNING [tx …]`, or `Pause refused WRONG_STATE
    from …: the machine's words [tx …]`."""
    who = asker(d.rider, d.identity, d.operator)
    src = f" from {who}" if who else ""
    again = " again (a repeat: answered as before, nothing done twice)" if d.repeat else ""
    if d.accepted:
        now = f", now {d.state}" if d.state else ""
        return f"{words(d.command)} accepted{again}{src}{now}{tx(d.transaction_id)}"
    why = f": {d.message}" if d.message else ""
    return f"{words(d.command)} refused {d.code}{again}{src}{why}{tx(d.transaction_id)}"


def completion_text(d: CompletionEvent) -> str:
    """`Start finished: DONE (session complete) [tx …]`, as the UI's command log says it."""
    why = f" ({d.reason})" if d.reason else ""
    now = f", now {d.state}" if d.state.value != d.outcome else ""
    return f"{words(d.command)} finished: {d.outcome}{why}{now}{tx(d.transaction_id)}"


def state_text(d: StateEvent) -> str:
    return f"{d.old} → {d.new}" + (f" ({d.reason})" if d.reason else "")


def fault_text(d: FaultEvent) -> str:
    axis = f" on the {d.axis} axis" if d.axis else ""
    verb = "cleared" if d.kind == "fault_cleared" else "raised"
    return f"{d.code} {verb}{axis}" + (f": {d.message}" if d.message else "")


ESTOP_WORDS = {
    "estop_pressed": "E-stop pressed",
    "estop_released": "E-stop released",
    "estop_latched": "E-stop latch set",
    "estop_reset": "E-stop latch reset",
}


def estop_text(d: EstopEvent) -> str:
    """`E-stop latch set (E-stop pressed), machine in FAULT_ESTOP`."""
    why = f" ({d.reason})" if d.reason else ""
    now = f", machine in {d.state}" if d.state else ""
    return f"{ESTOP_WORDS[d.kind]}{why}{now}"


def plural(n: int, one: str) -> str:
    return f"{n} {one}" if n == 1 else f"{n} {one}s"


def session_started_text(d: SessionStartedEvent) -> str:
    """`“default”: 2 steps, 3 revolutions [tx …]`."""
    size = f"{plural(d.steps, 'step')}, {plural(d.revolutions_total, 'revolution')}"
    return f"“{d.name}”: {size}{tx(d.transaction_id)}"


def session_ended_text(d: SessionEndedEvent) -> str:
    """`“default” DONE: 2 of 2 steps, 3 of 3 revolutions in 2.0 s`."""
    done = f"{d.steps_done} of {plural(d.steps, 'step')}"
    revs = f"{d.revolutions_done} of {plural(d.revolutions_total, 'revolution')}"
    return f"“{d.name}” {d.outcome}: {done}, {revs} in {duration(d.duration_s)}"


def calibration_values(values: Mapping[str, Any], *, when: bool) -> str:
    """`revolution 4.000 s, home arc 9.9° (measured)`; `when`: with the time it was taken."""
    parts = []
    for key, value in values.items():
        if key in QUANTITIES and isinstance(value, int | float):
            word, unit, decimals = QUANTITIES[key]
            parts.append(f"{word} {with_unit(fixed(value, decimals), unit)}")
        elif key not in ("source", "at", "verified"):
            parts.append(f"{key.replace('_', ' ')} {plain(value)}")
    how = [str(values.get("source") or "measured")]
    if values.get("verified") is not None and not values["verified"]:
        how.append("not verified yet")
    at = values.get("at")
    if when and isinstance(at, int | float) and math.isfinite(at):
        how.append(local_time(at))
    return f"{', '.join(parts)} ({', '.join(how)})"


def calibration_text(d: CalibrationEvent) -> str:
    """`rotate calibrated: revolution 4.000 s, home arc 9.9° (measured); before: …`."""
    saved = "" if d.persisted else "; NOT SAVED: lost at the next restart"
    if d.new is None:
        head = f"{d.axis} calibration dropped"
    else:
        head = f"{d.axis} calibrated: {calibration_values(d.new, when=False)}"
    before = f"; before: {calibration_values(d.old, when=True)}" if d.old else ""
    return f"{head}{before}{saved}"


def param_text(d: ParamEvent) -> str:
    """`tilt.max_deg set 45° → 50° by bay1 · 9d617a [tx …]`; a refusal says why."""
    old, new = param_value(d.name, d.old), param_value(d.name, d.new)
    what = f"reset to its default {new} (was {old})" if d.reset else f"set {old} → {new}"
    who = asker(d.by, d.identity, d.operator)
    src = f" by {who}" if who else ""
    if not d.accepted:
        return f"{d.name} {what}{src} refused: {d.message}{tx(d.transaction_id)}"
    saved = "" if d.persisted else "; NOT SAVED: back to the old value at the next restart"
    return f"{d.name} {what}{src}{saved}{tx(d.transaction_id)}"


def rider_text(d: RiderEvent) -> str:
    """A departure at rest or mid-motion (common/departure.py); a return; or what a machine
    older than `mid_motion` said."""
    who = rider_name(d.rider)
    if d.kind == "rider_lost" and d.mid_motion is not None:
        return departure_text(who, d.policy, d.acted, d.mid_motion)
    verb = "lost" if d.kind == "rider_lost" else "back"
    if not d.policy:
        return f"rider {who} {verb}"
    acted = (", applied at once" if d.acted else ", not applied at once") if verb == "lost" else ""
    return f"rider {who} {verb} (policy {d.policy}{acted})"


def watchdog_text(d: WatchdogEvent) -> str:
    return f"scan loop stalled {duration(d.stalled_s)}: outputs forced safe"


def clock_text(d: ClockEvent) -> str:
    way = "forward" if d.step_s >= 0 else "back"
    return f"host clock set {way} by {duration(d.step_s)} (wall times follow it from here)"


def daemon_start_text(d: DaemonStartEvent) -> str:
    period = with_unit(trimmed(d.period_s * 1000, 3), "ms")
    unclean = "; the previous run did not stop cleanly" if d.previous_stop_clean is False else ""
    return f"pid {d.pid}, {d.hal} HAL, scan period {period}{unclean}"


def daemon_stop_text(d: DaemonStopEvent) -> str:
    return f"{d.reason}, exit code {d.exit_code}"


def storage_text(d: StorageEvent) -> str:
    lost = f"; {plural(d.lost, 'event')} lost" if d.lost else ""
    return f"writing {d.what} failed: {d.error}{lost}"


def dropped_text(d: DroppedEvent) -> str:
    return f"{plural(d.count, 'event')} dropped (the writer's queue was full)"


TEXTS: dict[str, Callable[[Any], str]] = {
    EventKind.COMMAND: command_text,
    EventKind.COMPLETION: completion_text,
    EventKind.STATE: state_text,
    EventKind.FAULT_RAISED: fault_text,
    EventKind.FAULT_CLEARED: fault_text,
    EventKind.ESTOP_PRESSED: estop_text,
    EventKind.ESTOP_RELEASED: estop_text,
    EventKind.ESTOP_LATCHED: estop_text,
    EventKind.ESTOP_RESET: estop_text,
    EventKind.SESSION_STARTED: session_started_text,
    EventKind.SESSION_ENDED: session_ended_text,
    EventKind.CALIBRATION: calibration_text,
    EventKind.PARAM_CHANGED: param_text,
    EventKind.SAFETY_CHANGED: param_text,
    EventKind.RIDER_LOST: rider_text,
    EventKind.RIDER_RETURNED: rider_text,
    EventKind.WATCHDOG_TRIP: watchdog_text,
    EventKind.CLOCK_SET: clock_text,
    EventKind.DAEMON_START: daemon_start_text,
    EventKind.DAEMON_STOP: daemon_stop_text,
    EventKind.STORAGE_FAILED: storage_text,
    EventKind.EVENTS_DROPPED: dropped_text,
}
"""The text of each kind of event."""
assert set(TEXTS) == set(EventKind), "every kind of event needs its text"


def plain(value: Any) -> str:
    """A value of a kind this reader does not know, without Python's punctuation."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | float):
        return number(value)
    if value is None:
        return "none"
    if isinstance(value, Mapping):
        return ", ".join(f"{k} {plain(v)}" for k, v in value.items())
    if isinstance(value, list | tuple):
        return ", ".join(plain(v) for v in value)
    return str(value)


def describe(details: Details) -> str:
    """One line for people about an event's details (the CLI's, the UI's and the export's text).
    A kind newer than this reader: its fields as `name value`, separated by ` · `."""
    if isinstance(details, dict):
        fields = [f"{k.replace('_', ' ')} {plain(v)}" for k, v in details.items() if k != "kind"]
        return " · ".join(fields)
    return TEXTS[details.kind](details)


__all__ = ["asker", "describe", "rider_name"]
