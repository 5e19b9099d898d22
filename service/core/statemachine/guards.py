"""The table's guards: which target a row's `Pick` chooses, and which command the machine
refuses, as predicates of one `Facts` value taken when a trigger is judged.

Nothing here reads the machine: the state machine takes its `Facts` (`StateMachine.facts`)
and these say what follows from them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from ride_machine.schema.commands import RotateStep, Session, TiltStep
from ride_machine.schema.status import MOTION_STATES, MachineState
from ride_machine.service.config.axes import TiltSection
from ride_machine.service.errors import DuplicateId, EstopActive, MachineError, WrongState

from .table import Accepts, Pick, Rule

S = MachineState


class Facts(NamedTuple):
    """What the guards read, taken at once (a tuple: made for every command, in its reply's
    path, at under half a frozen dataclass's cost)."""

    uncalibrated: tuple[str, ...]
    """The axes without a calibration."""
    not_home: tuple[str, ...]
    """The axes without a reference, or off their home switch now."""
    resume_to: MachineState | None
    """The state Pause interrupted."""
    estop_from: MachineState | None
    """The state the E-stop interrupted."""
    runnable: bool
    """A controller is left to run (paused, or held by the E-stop)."""
    stop_on_loss: bool
    """`rider_loss.policy` is stop (else pause)."""
    estop: bool
    """The E-stop input as scanned."""
    held_by: tuple[str, ...]
    """Other sessions holding this machine's id."""
    session: Session | None = None
    """The session Start's checks judge (None: not a Start)."""
    bad_session: tuple[str, str] | None = None
    """The first of its steps this machine cannot do: (path, message)."""


def rest(facts: Facts) -> MachineState:
    """IDLE when calibrated and home, else the warning that says why."""
    if facts.uncalibrated:
        return S.WARNING_NEEDS_CALIBRATION
    return S.WARNING_NOT_HOME if facts.not_home else S.IDLE


def _before(interrupted: MachineState | None, facts: Facts) -> MachineState:
    """The interrupted state, or the rest state if it was a motion with nothing to run."""
    to = interrupted or rest(facts)
    if to in MOTION_STATES and not facts.runnable:
        return rest(facts)
    return to


def start_checks(facts: Facts) -> MachineState:
    """The state of the first of Start's checks that fails, else RUNNING."""
    if facts.uncalibrated:
        return S.WARNING_NEEDS_CALIBRATION
    if facts.not_home:
        return S.WARNING_NOT_HOME
    return S.FAULT_HW if facts.bad_session is not None else S.RUNNING


PICKS: dict[Pick, Callable[[Facts], MachineState]] = {
    Pick.REST: rest,
    Pick.BEFORE_PAUSE: lambda facts: _before(facts.resume_to, facts),
    Pick.BEFORE_ESTOP: lambda facts: _before(facts.estop_from, facts),
    Pick.START_CHECKS: start_checks,
    Pick.POLICY: lambda facts: S.DONE if facts.stop_on_loss else S.PAUSED,
}
"""How each `Pick` chooses, from the facts alone."""


def choose(rule: Rule, facts: Facts) -> MachineState:
    """The row's target: its only one, or the one its `Pick` chooses."""
    return rule.targets[0] if rule.pick is None else PICKS[rule.pick](facts)


def refusal(
    accepts: Accepts, state: MachineState, facts: Facts, machine_id: str
) -> MachineError | None:
    """Why this machine cannot take the command `accepts` describes in `state` now (its id
    held twice, the E-stop, a state none of its rows leaves from), or None."""
    held_by, name = facts.held_by, accepts.name
    if held_by:
        return DuplicateId(
            f"{name} refused: machine id {machine_id} is also held by"
            f" session {', '.join(held_by)}; nothing is taken until one of the"
            " two daemons is stopped or given another id"
        )
    if facts.estop:
        return EstopActive(
            f"{name} refused: the E-stop is active; release it, then Resume, Home or Stop"
        )
    if state not in accepts.states:
        return WrongState(f"{name} is not accepted in state {state}; accepted in: {accepts.text}")
    return None


def session_problem(session: Session, tilt: TiltSection) -> tuple[str, str] | None:
    """The first step this machine cannot do, as (JSON pointer, message)."""
    lo, hi = tilt.min_deg, tilt.max_deg
    for i, step in enumerate(session.steps):
        if isinstance(step, TiltStep) and not lo <= step.degrees <= hi:
            return (
                f"/session/steps/{i}/degrees",
                f"step {i}: tilt {step.degrees:g}° is outside this machine's range {lo:g}..{hi:g}°",
            )
        if isinstance(step, RotateStep) and step.revolutions < 1:
            return (f"/session/steps/{i}/revolutions", f"step {i}: revolutions must be ≥ 1")
    return None
