"""The motion context: what a motion command begins, what it leaves behind, and how it ended.

A motion (Home, Calibrate*, Start) is one `Motion` from `begin` until its one completion
notice, like a ROS 2 action goal; its controller, session, and where Pause or the E-stop
interrupted it are its `Drive`, reset in one go when it is cleared. `MotionContext` owns the
three (drive, action, notices not yet taken); the state machine changes the state around it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ride_machine.schema.commands import Command
from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.status import FaultCode, MachineState, MotionRef
from ride_machine.service.config.model import LiveConfig
from ride_machine.service.core.motion.base import Controller
from ride_machine.service.core.motion.controllers import SessionRun
from ride_machine.service.core.motion.devices import Devices


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
    """What a motion command begins: its controller runs in the state the table leads the
    command to, and `on_done` (bound now) acts when it finishes and says how it ended."""

    command: Command
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


class MotionContext:
    """The motion under way (`action`), what drives it (`drive`), and the completion notices
    produced and not yet taken by the scan loop (`completions`)."""

    def __init__(self, devices: Devices, live: LiveConfig) -> None:
        self.devices = devices
        self.live = live
        self.drive = Drive()
        self.action: Motion | None = None
        """The motion command whose completion notice is still due (running, paused,
        E-stopped), like a ROS 2 action goal."""
        self.completions: list[Completion] = []
        """Notices produced and not yet taken (`take`)."""

    def begin(self, plan: Plan, motion: Motion, state: MachineState, wall: float) -> None:
        """`motion` is under way from `wall`, driven by `plan`, begun in `state`. Only a motion
        halted by the E-stop can be replaced (Home, Calibrate*): it ended, replaced."""
        by = motion.command.value
        if state is MachineState.FAULT_ESTOP:
            why = f"halted by the E-stop and not resumed; replaced by {by}"
            self.end(Ending(Outcome.FAULT_ESTOP, why, FaultCode.ESTOP.value), state, wall)
        else:
            self.end(Ending(Outcome.STOPPED, f"replaced by {by}"), state, wall)
        self.clear()
        self.drive = Drive(controller=plan.controller, session_run=plan.session)
        self.action = motion

    def clear(self) -> None:
        """Abandon the controller (outputs off) and forget the session, where Pause and the
        E-stop came from, and the E-stop latch: a new motion, Stop or a fault starts clean."""
        if self.drive.controller is not None:
            self.drive.controller.abandon()
        self.drive = Drive()
        self.devices.stop_all()

    def pause(self, interrupted: MachineState) -> None:
        """Halt the controller; Resume goes back to `interrupted`."""
        if self.drive.controller is not None:
            self.drive.controller.halt()
        self.drive.resume_to = interrupted

    def estop(self, interrupted: MachineState | None) -> None:
        """Halt, outputs off; latched, with the state it interrupted (None: latched already)."""
        if self.drive.controller is not None:
            self.drive.controller.halt()
        self.devices.stop_all()
        if interrupted is not None:
            self.drive.estop_from = interrupted
            self.drive.estop_latched = True

    def resume(self, after_estop: bool, moving: bool, now: float) -> None:
        """Forget what Pause (or the E-stop: its latch too) interrupted; `moving`: the
        controller goes on."""
        drive = self.drive
        if after_estop:
            drive.estop_latched = False
            drive.estop_from = None
        else:
            drive.resume_to = None
        if moving:
            assert drive.controller is not None  # `Pick.BEFORE_*` chose a motion to run
            drive.controller.resume(now)

    def end(self, ending: Ending, state: MachineState, wall: float) -> None:
        """The running motion has ended: its one notice (nothing if none is running)."""
        motion, self.action = self.action, None
        if motion is not None:
            self.notify(motion, ending, state, wall)

    def notify(self, motion: Motion, ending: Ending, state: MachineState, wall: float) -> None:
        """`motion`'s completion notice: it ended as `ending`, in `state`, at `wall`."""
        self.completions.append(
            Completion(
                machine_id=self.live.current.machine.id,
                transaction_id=motion.transaction_id,
                command=motion.command.value,
                outcome=ending.outcome,
                code=ending.code,
                reason=ending.reason,
                state=state,
                rider=motion.rider,
                started_at=motion.started_at,
                time=wall,
            )
        )

    def take(self) -> list[Completion]:
        """The notices produced since the last call (the scan loop publishes them)."""
        out, self.completions = self.completions, []
        return out

    def at_rest(self) -> bool:
        """No controller to step, no notice for the loop to take."""
        return self.drive.controller is None and not self.completions

    def active(self) -> Controller | None:
        """The controller that owns an axis now (running, paused or held by an E-stop)."""
        ctl = self.drive.controller
        return ctl.active() if ctl is not None else None
