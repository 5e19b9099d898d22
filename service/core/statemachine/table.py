"""The machine's behaviour as data: every `(trigger, states) → targets` row, and its vocabulary.

`TABLE` is what runs: the state machine looks up where a trigger leads (`ROWS`), lets a row
with several targets choose by its `Pick`, and refuses any state change that is not one of its
rows (`IllegalTransition`: a bug, raised loudly). The command guard reads the rows' sources
(`ACCEPTS`); the
README's state table and docs/states.md are generated from them (`python -m
service.core.statemachine.control_doc`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, StrEnum

from ride_machine.schema.commands import ALLOWED_STATES, REST_STATES, Command, ReplyCode
from ride_machine.schema.status import MOTION_STATES, MachineState

S = MachineState


class Occurrence(StrEnum):
    """What changes the state besides a command: the table's rows that no Rider sends."""

    POWER_UP = "power-up"
    ESTOP = "E-stop pressed"
    MOTION_DONE = "motion done"
    MOTION_FAULT = "motion fault"
    SAVED = "calibration saved"
    RIDER_LOST = "Rider lost"
    FAULT = "fault"
    CALIBRATION_ENTERED = "calibration entered"


Trigger = Command | Occurrence


class Pick(Enum):
    """How a row with several targets chooses one, from the facts it names (guards.py)."""

    REST = "the rest state: IDLE when calibrated and home, else the warning that says why"
    BEFORE_PAUSE = "the state Pause interrupted; the rest state if nothing is left to run"
    BEFORE_ESTOP = "the state the E-stop interrupted; the rest state if nothing is left to run"
    START_CHECKS = "the state of the first of Start's checks that fails; RUNNING if all pass"
    POLICY = "rider_loss.policy: pause → PAUSED, stop → DONE"


@dataclass(frozen=True, slots=True)
class Rule:
    """One row of the machine's behaviour: `trigger` in any of `sources` leads to one of
    `targets` (chosen by `pick` when there are several) or leaves the state as it is."""

    trigger: Trigger
    sources: frozenset[MachineState]
    targets: tuple[MachineState, ...]
    does: str
    """The action in the docs' words."""
    pick: Pick | None = None


@dataclass(frozen=True, slots=True)
class Handling:
    """What a command earns: its reply, and how the guard and the bus treat it (its action is
    in `handlers.ACTIONS`)."""

    reply: ReplyCode
    read_only: bool = False
    """Answered in every state, even with the E-stop active or the machine id held twice."""
    moves: bool = False
    """Sets the machine moving: its sender becomes the controlling Rider."""


@dataclass(frozen=True, slots=True)
class Transition:
    """A state change, for the log and for observers."""

    old: MachineState
    new: MachineState
    reason: str
    at: float


class IllegalTransition(RuntimeError):
    """A state change that no row of `TABLE` allows: a bug in the state machine. On the scan
    thread the runner turns it into a FAULT_HW with the outputs safe, like any exception."""

    def __init__(
        self, trigger: Trigger, old: MachineState | None, new: MachineState | None
    ) -> None:
        """`old` None: before power-up; `new` None: the trigger has no row in `old`."""
        super().__init__(f"{trigger}: {old} → {new} is not in the transition table")
        self.trigger, self.old, self.new = trigger, old, new


_ANY = frozenset(S)
_REST = (S.IDLE, S.WARNING_NOT_HOME, S.WARNING_NEEDS_CALIBRATION)
"""The rest state, in the order it is chosen: IDLE when calibrated and home, else the warning."""
_C, _R, _E = Command, ReplyCode, Occurrence


def _to_rest(
    trigger: Trigger, sources: set[MachineState] | frozenset[MachineState], does: str
) -> Rule:
    """A row that leads to the rest state, whichever it is now."""
    return Rule(trigger, frozenset(sources), _REST, does, Pick.REST)


HANDLING: dict[Command, Handling] = {
    _C.CALIBRATE_TILT: Handling(_R.RESP_CALIBRATION_ACCEPTED, moves=True),
    _C.CALIBRATE_ROTATE: Handling(_R.RESP_CALIBRATION_ACCEPTED, moves=True),
    _C.HOME: Handling(_R.RESP_HOME_ACCEPTED, moves=True),
    _C.START: Handling(_R.RESP_START_ACCEPTED, moves=True),
    _C.PAUSE: Handling(_R.RESP_PAUSED),
    _C.RESUME: Handling(_R.RESP_RESUMED, moves=True),
    _C.STOP: Handling(_R.RESP_DONE),
    _C.CHECK_CALIBRATION: Handling(_R.RESP_CHECK, read_only=True),
    _C.CHECK_HOME: Handling(_R.RESP_CHECK, read_only=True),
}
"""Each command's reply and kind."""

TABLE: tuple[Rule, ...] = (
    # Commands, in the order of `Command`: accepted in `sources` (E-stop released); where one
    # row says it, that is ALLOWED_STATES (schema/commands.py, which the Rider reads too).
    Rule(
        _C.CALIBRATE_TILT,
        ALLOWED_STATES[_C.CALIBRATE_TILT],
        (S.CALIBRATING,),
        "tilt: latch the zero, a stroke up (gain), latch the zero again; both must agree",
    ),
    Rule(
        _C.CALIBRATE_ROTATE,
        ALLOWED_STATES[_C.CALIBRATE_ROTATE],
        (S.CALIBRATING,),
        "tilt home, rotate home, then time the revolution twice; both must agree",
    ),
    Rule(_C.HOME, ALLOWED_STATES[_C.HOME], (S.HOMING,), "tilt, then rotate: each edge latched"),
    Rule(
        _C.START,
        ALLOWED_STATES[_C.START],
        (S.RUNNING, S.WARNING_NEEDS_CALIBRATION, S.WARNING_NOT_HOME, S.FAULT_HW),
        "runs the session (default: tilt 45°, one CW revolution ×3); refused: not calibrated →"
        " WARNING_NEEDS_CALIBRATION, not home → WARNING_NOT_HOME, invalid session → FAULT_HW",
        Pick.START_CHECKS,
    ),
    Rule(_C.PAUSE, ALLOWED_STATES[_C.PAUSE], (S.PAUSED,), "controller halted, relays off"),
    Rule(
        _C.RESUME,
        frozenset({S.PAUSED}),
        (S.HOMING, S.CALIBRATING, S.RUNNING, *_REST),
        "back to the state before Pause (the rest state if nothing is left to run)",
        Pick.BEFORE_PAUSE,
    ),
    Rule(
        _C.RESUME,
        frozenset({S.FAULT_ESTOP}),
        tuple(s for s in S if s is not S.FAULT_ESTOP),
        "back to the state before the E-stop (a motion goes on)",
        Pick.BEFORE_ESTOP,
    ),
    Rule(_C.STOP, ALLOWED_STATES[_C.STOP], (S.DONE,), "controllers stopped, session cleared"),
    Rule(
        _C.CHECK_CALIBRATION,
        frozenset({S.IDLE, S.DONE, S.WARNING_NOT_HOME}),
        (S.WARNING_NEEDS_CALIBRATION,),
        "not calibrated → WARNING_NEEDS_CALIBRATION",
    ),
    Rule(
        _C.CHECK_CALIBRATION,
        frozenset({S.WARNING_NEEDS_CALIBRATION}),
        (S.IDLE, S.WARNING_NOT_HOME),
        "passed → the rest state",
        Pick.REST,
    ),
    Rule(
        _C.CHECK_CALIBRATION,
        _ANY - REST_STATES,
        (),
        "outside the rest states it only answers",
    ),
    Rule(
        _C.CHECK_HOME,
        frozenset({S.IDLE, S.DONE}),
        (S.WARNING_NOT_HOME,),
        "not home → WARNING_NOT_HOME",
    ),
    Rule(
        _C.CHECK_HOME,
        frozenset({S.WARNING_NOT_HOME}),
        (S.IDLE, S.WARNING_NEEDS_CALIBRATION),
        "passed → the rest state",
        Pick.REST,
    ),
    Rule(
        _C.CHECK_HOME,
        _ANY - {S.IDLE, S.DONE, S.WARNING_NOT_HOME},
        (),
        "elsewhere it only answers (WARNING_NEEDS_CALIBRATION, the bigger problem, stays)",
    ),
    # Events.
    Rule(
        _E.POWER_UP,
        frozenset(),
        (S.WARNING_NEEDS_CALIBRATION, S.WARNING_NOT_HOME),
        "outputs safe; never assumed home",
        Pick.REST,
    ),
    Rule(
        _E.ESTOP,
        _ANY - {S.FAULT_ESTOP},
        (S.FAULT_ESTOP,),
        "relays dropped in the same cycle, controller halted, latched",
    ),
    _to_rest(_E.MOTION_DONE, {S.HOMING}, "both axes referenced; the rest state"),
    _to_rest(
        _E.MOTION_DONE, {S.CALIBRATING}, "calibration in use; the rest state once it is saved"
    ),
    Rule(_E.MOTION_DONE, frozenset({S.RUNNING}), (S.DONE,), "session complete"),
    _to_rest(
        _E.SAVED,
        {S.CALIBRATING},
        "the calibration's write ended (its notice says whether it was saved)",
    ),
    Rule(
        _E.MOTION_FAULT,
        MOTION_STATES,
        (S.FAULT_HW,),
        "sensor timeout, stuck switch, implausible speed or measurement, an edge not latched,"
        " calibration not repeatable: outputs off, references lost",
    ),
    Rule(
        _E.FAULT,
        _ANY - {S.FAULT_HW},
        (S.FAULT_HW,),
        "watchdog, supervisor, loop exception, a second daemon with this id",
    ),
    Rule(
        _E.RIDER_LOST,
        MOTION_STATES,
        (S.PAUSED, S.DONE),
        "rider_loss.policy pause → PAUSED, stop → DONE (after rider_loss.grace_s)",
        Pick.POLICY,
    ),
    _to_rest(
        _E.CALIBRATION_ENTERED,
        REST_STATES - {S.DONE},
        "a technician's values: the rest state (that axis not home until Home checks them)",
    ),
)
"""The machine's behaviour, row by row: it chooses each target and allows each state change."""


def _index() -> dict[tuple[Trigger, MachineState], Rule]:
    """The row of each (trigger, state): at most one, and a row with several targets picks."""
    rows: dict[tuple[Trigger, MachineState], Rule] = {}
    for rule in TABLE:
        assert (len(rule.targets) > 1) is (rule.pick is not None), rule
        for state in rule.sources:
            assert (rule.trigger, state) not in rows, (rule.trigger, state)
            rows[rule.trigger, state] = rule
    return rows


ROWS = _index()
"""`(trigger, state) → Rule`: what the machine does, looked up in one step."""
POWER_UP = next(r for r in TABLE if r.trigger is Occurrence.POWER_UP)
"""The row the machine starts by (it has no source state)."""

ONLY: dict[Trigger, MachineState] = {
    trigger: targets.pop()
    for trigger in (*Command, *Occurrence)
    if len(targets := {t for r in TABLE if r.trigger is trigger for t in r.targets}) == 1
}
"""Triggers that lead to one state only (E-stop, a fault): met there already, they change
nothing (a fault while faulted replaces the fault, not the state)."""


EDGES = frozenset((s, t) for r in TABLE for s in r.sources for t in r.targets if s is not t)
"""Every (old, new) state change the table allows."""


def edges() -> frozenset[tuple[MachineState, MachineState]]:
    """Every (old, new) state change the table allows."""
    return EDGES


@dataclass(frozen=True, slots=True)
class Accepts:
    """Where a command is taken, as its rows say: the states, and how a refusal names them."""

    name: str
    states: frozenset[MachineState]
    text: str
    """The states, sorted once (a WRONG_STATE refusal per command under a storm)."""


def _accepts(command: Command) -> Accepts:
    states = frozenset().union(*(r.sources for r in TABLE if r.trigger is command))
    return Accepts(command.value, states, ", ".join(sorted(states)))


ACCEPTS = {command: _accepts(command) for command in Command}
"""Each command's states, from the rows (the command guard reads them, guards.py)."""


def allowed_states(command: Command) -> frozenset[MachineState]:
    """The states in which `command` is accepted (E-stop released), as the table says."""
    return ACCEPTS[command].states
