"""What the page needs to know and must not hard-code: commands, where they are accepted,
state colours and the session presets. Served as `/api/config`, built from `schema/`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ride_machine.schema.commands import (
    ALLOWED_STATES,
    DEFAULT_SESSION,
    READ_ONLY_COMMANDS,
    Command,
    Direction,
    RotateStep,
    Session,
    TiltStep,
)
from ride_machine.schema.events import Details, EventKind, RiderEvent
from ride_machine.schema.status import FAULT_STATES, MOTION_STATES, MachineState

S = MachineState


@dataclass(frozen=True)
class CommandInfo:
    """A command as the page shows it: a label and, for motion, a confirmation question."""

    command: Command
    label: str
    confirm: str | None = None


COMMANDS = [
    CommandInfo(Command.CALIBRATE_TILT, "Calibrate tilt"),
    CommandInfo(Command.CALIBRATE_ROTATE, "Calibrate rotate"),
    CommandInfo(
        Command.HOME,
        "Home",
        "Home both axes? The seat tilts to 0° and then rotates to its home switch.",
    ),
    CommandInfo(Command.START, "Start", "Start the session? The ride will move."),
    CommandInfo(Command.PAUSE, "Pause"),
    CommandInfo(Command.RESUME, "Resume"),
    CommandInfo(Command.STOP, "Stop"),
    CommandInfo(Command.CHECK_CALIBRATION, "Check calibration"),
    CommandInfo(Command.CHECK_HOME, "Check home"),
]
assert {c.command for c in COMMANDS} == set(Command), "every command needs a button"

BY_KEY = {c.command.key: c for c in COMMANDS}


def state_tone(state: MachineState) -> str:
    """The colour family an operator reads at a glance: ok (green), warn (amber), fault (red)."""
    if state in FAULT_STATES:
        return "fault"
    if state is S.PAUSED or state.value.startswith("WARNING_"):
        return "warn"
    if state in MOTION_STATES:
        return "moving"
    return "ok"


STATE_HINTS: dict[MachineState, str] = {
    S.WARNING_NEEDS_CALIBRATION: "Not calibrated: run Calibrate tilt and Calibrate rotate.",
    S.WARNING_NOT_HOME: "Not home: press Home before Start.",
    S.PAUSED: "Paused, outputs off: Resume continues, Stop ends the session.",
    S.FAULT_HW: "Hardware fault, outputs off: fix the cause, then Home or calibrate again.",
    S.FAULT_ESTOP: "Released but latched: Resume returns to the previous state, Home re-homes,"
    " Stop ends the session.",
}
"""One line per state that needs the operator, shown in the banner."""

ESTOP_PRESSED_HINT = "Outputs off. Release the E-stop, then Resume, Home or Stop."


SESSION_PRESETS: list[tuple[str, str, Session]] = [
    ("default", "Default: tilt 45°, 3 revolutions CW", DEFAULT_SESSION),
    (
        "gentle",
        "Gentle: tilt 15°, 1 revolution CW, back to 0°",
        Session(
            name="gentle",
            steps=[TiltStep(degrees=15.0), RotateStep(revolutions=1), TiltStep(degrees=0.0)],
        ),
    ),
    (
        "twist",
        "Twist: tilt 30°, 2 CW, 2 CCW, back to 0°",
        Session(
            name="twist",
            steps=[
                TiltStep(degrees=30.0),
                RotateStep(direction=Direction.CW, revolutions=2),
                RotateStep(direction=Direction.CCW, revolutions=2),
                TiltStep(degrees=0.0),
            ],
        ),
    ),
    (
        "thrill",
        "Thrill: tilt 60°, 5 revolutions CW, back to 0°",
        Session(
            name="thrill",
            steps=[TiltStep(degrees=60.0), RotateStep(revolutions=5), TiltStep(degrees=0.0)],
        ),
    ),
]


EVENTS_SHOWN = 50
"""How many of the newest events the Events panel lists."""

INCIDENTS = frozenset(
    {
        EventKind.FAULT_RAISED,
        EventKind.ESTOP_PRESSED,
        EventKind.ESTOP_LATCHED,
        EventKind.WATCHDOG_TRIP,
        EventKind.STORAGE_FAILED,
        EventKind.EVENTS_DROPPED,
        EventKind.RIDER_LOST,
    }
)
"""Kinds of event an operator must look into: shown in red."""


def event_tone(details: Details) -> str:
    """`fault` (red) for an incident, else ``. A Rider that left the machine at rest is
    routine; one lost mid-motion is not (nor one an older machine could not tell apart)."""
    if isinstance(details, RiderEvent):
        lost = details.kind == "rider_lost" and details.mid_motion is not False
        return "fault" if lost else ""
    kind = details.get("kind") if isinstance(details, dict) else details.kind
    return "fault" if kind in INCIDENTS else ""


def ui_config(*, monitor: bool, lost_after_s: float, history_s: float) -> dict[str, Any]:
    """The `/api/config` document."""
    return {
        "monitor": monitor,
        "lost_after_s": lost_after_s,
        "history_s": history_s,
        "commands": [
            {
                "name": c.command.value,
                "key": c.command.key,
                "label": c.label,
                "confirm": c.confirm,
                "states": sorted(ALLOWED_STATES[c.command]),
                "with_estop": c.command in READ_ONLY_COMMANDS,
            }
            for c in COMMANDS
        ],
        "tones": {s.value: state_tone(s) for s in MachineState},
        "hints": {s.value: hint for s, hint in STATE_HINTS.items()},
        "estop_pressed": ESTOP_PRESSED_HINT,
        "event_kinds": [k.value for k in EventKind],
        "events_shown": EVENTS_SHOWN,
        "sessions": [
            {"id": sid, "label": label, "session": session.model_dump(mode="json")}
            for sid, label, session in SESSION_PRESETS
        ],
    }
