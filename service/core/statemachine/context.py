"""The motion context: what a motion command begins, what it leaves behind, and how it ended.

A motion (Home, Calibrate*, Start) is one `Motion` from `begin` until its one completion
notice, like a ROS 2 action goal; its controller, session, and where Pause or the E-stop
interrupted it are its `Drive`, reset in one go when it is cleared.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from schema.commands import Command
from schema.completion import Outcome
from schema.status import MachineState, MotionRef
from service.core.controllers import SessionRun
from service.core.motion import Controller

if TYPE_CHECKING:  # types only: the state machine does no IO
    from service.core.persist import SaveTicket


@dataclass(frozen=True, slots=True)
class Ending:
    """How a motion ended, before it becomes a `Completion` notice."""

    outcome: Outcome
    reason: str
    code: str | None = None


OnDone = Callable[[float], "Ending | None"]
"""What a motion's end does besides the state change the table makes, bound when the motion
begins: it says how the motion ended (None: not ended yet, e.g. a calibration being saved)."""


def never(now: float) -> Ending | None:
    """The `on_done` of a notice that ends a command before any motion began."""
    raise AssertionError("no controller runs for a refused Start")


@dataclass(frozen=True, slots=True)
class Plan:
    """What a motion command begins: its controller runs in `state` (the table's target), and
    `on_done` (bound now) acts when it finishes and says how the motion ended."""

    command: Command
    state: MachineState
    controller: Controller
    on_done: OnDone
    why: str | None = None
    """The transition's reason (default: the command)."""
    session: SessionRun | None = None
    """The run whose progress the status shows (Start)."""


@dataclass(frozen=True, slots=True)
class Motion:
    """An accepted motion command, from `begin` until its one completion notice."""

    command: Command
    transaction_id: str
    rider: str | None
    started_at: float
    """Wall-clock seconds."""
    on_done: OnDone

    def ref(self) -> MotionRef:
        return MotionRef(
            transaction_id=self.transaction_id,
            command=self.command.value,
            started_at=self.started_at,
        )


@dataclass(slots=True)
class Drive:
    """What a motion leaves behind until the machine clears it in one go."""

    controller: Controller | None = None
    """Drives the axes: running, paused or held by an E-stop (None once finished)."""
    session_run: SessionRun | None = None
    """The session's progress; kept after it ends so the status shows how far it went."""
    resume_to: MachineState | None = None
    """The state Pause interrupted."""
    estop_from: MachineState | None = None
    """The state the E-stop interrupted."""
    estop_latched: bool = False


@dataclass(frozen=True, slots=True)
class Saving:
    """A calibration's write under way, and the motion whose notice waits for it."""

    ticket: SaveTicket
    motion: Motion | None


@dataclass(slots=True)
class Refs:
    """Which axes have a position reference since power-up or the last hardware fault."""

    tilt: bool = False
    rotate: bool = False
