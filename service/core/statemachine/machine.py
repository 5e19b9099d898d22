"""`StateMachine`: the machine's states, run by the table. Pure logic: no IO, no clock, time in.

Commands come in through `handle` (their actions: handlers.py), the scan cycle through
`on_estop` and `update`. Where a trigger leads is the table's to say (`target`: its row, and
the row's `Pick` when it has several targets), and every state change goes through `enter`,
which refuses any the table does not have (`IllegalTransition`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from schema.calibration import CalibrationSet
from schema.commands import Command, CommandRequest, Reply, Session
from schema.completion import Completion, Outcome
from schema.status import (
    MOTION_STATES,
    AxesFlags,
    Fault,
    FaultCode,
    MachineState,
    SessionProgress,
)
from service.config.model import LiveConfig, MachineConfig, RiderLossPolicy
from service.core.controllers import SessionRun
from service.core.devices import Calibration, Devices
from service.core.motion import Controller, Step
from service.core.statemachine import calibration, deadman, handlers
from service.core.statemachine.context import Drive, Ending, Motion, Plan, Refs, Saving
from service.core.statemachine.deadman import RiderWatch, Verdict
from service.core.statemachine.snapshot import Snapshot, snapshot_of
from service.core.statemachine.table import (
    POWER_UP,
    ROWS,
    Event,
    IllegalTransition,
    Pick,
    Rule,
    Transition,
    Trigger,
    row,
)

if TYPE_CHECKING:  # types only: the state machine does no IO
    from service.core.persist import SaveTicket, StorageHealth

S = MachineState


@dataclass(eq=False)
class StateMachine:
    """Commands in, a state and desired outputs out; `update(now)` once per scan cycle."""

    devices: Devices
    live: LiveConfig
    """The running config (online parameters change it between cycles): read, never kept."""
    calibration: Calibration = field(default_factory=Calibration)
    on_calibrated: Callable[[Calibration], SaveTicket | None] | None = None
    """Persist a new calibration; a ticket that is not done keeps CALIBRATING until it is."""
    storage: StorageHealth | None = None
    """What could not be written to the data dir: its warnings are part of the status."""
    on_transition: Callable[[Transition], None] | None = None
    wall_offset: float = 0.0
    warnings: list[str] = field(default_factory=list)
    """Warnings from start-up (a calibration or parameter file that could not be read)."""

    def __post_init__(self) -> None:
        self.devices.tilt.calibration = self.calibration.tilt
        self.refs = Refs()
        self.previous_state: MachineState | None = None
        self.fault: Fault | None = None
        self.drive = Drive()
        self.watch = RiderWatch()
        """The controlling Rider, as the deadman sees it."""
        self.duplicate_of: tuple[str, ...] = ()
        """Other sessions holding this machine's id (the bus watches `holder/<zid>`)."""
        self.action: Motion | None = None
        """The motion command whose completion notice is still due (running, paused,
        E-stopped), like a ROS 2 action goal; `motion()` is the controller driving it."""
        self.completions: list[Completion] = []
        """Notices produced and not yet taken by the scan loop (`take_completions`)."""
        self.saving: Saving | None = None
        self.save_ticket: SaveTicket | None = None
        """The write of the calibration in use (None: nothing to write it to, or not yet)."""
        self.state = self._pick(POWER_UP)  # never assumed home
        if self.state not in POWER_UP.targets:
            raise IllegalTransition(Event.POWER_UP, None, self.state)
        self.changes = 0
        """Calls that may have changed the machine: each public method that can counts itself
        first (the deadman only when it judged). The scan loop's quiet cycles compare it."""
        self.devices.stop_all()

    @property
    def config(self) -> MachineConfig:
        return self.live.current

    # The motion context and the controlling Rider, read-only from outside.
    @property
    def controller(self) -> Controller | None:
        return self.drive.controller

    @property
    def session_run(self) -> SessionRun | None:
        return self.drive.session_run

    @property
    def estop_latched(self) -> bool:
        return self.drive.estop_latched

    @property
    def controller_rider(self) -> str | None:
        return self.watch.id

    @property
    def rider_connected(self) -> bool:
        return self.watch.connected

    @property
    def rider_warning(self) -> str | None:
        return self.watch.warning

    # ------------------------------------------------------------------------- commands
    def handle(self, command: Command, request: CommandRequest, now: float) -> Reply:
        """Act on one command and say what happened (handlers.py); refusals change nothing
        but the reply."""
        self.changes += 1
        return handlers.handle(self, command, request, now)

    # ---------------------------------------------------------------------- the table
    def target(self, trigger: Trigger, session: Session | None = None) -> MachineState:
        """Where `trigger` leads from the current state: the table's row chooses (`session`:
        the one Start's checks judge)."""
        rule = row(trigger, self.state)
        if rule is None or not rule.targets:
            return self.state
        chosen = self._pick(rule, session)
        if chosen not in rule.targets:
            raise IllegalTransition(trigger, self.state, chosen)
        return chosen

    def go(self, trigger: Trigger, now: float, why: str) -> None:
        """The state change `trigger` makes now, as the table says."""
        self.enter(trigger, self.target(trigger), now, why)

    def enter(self, trigger: Trigger, new: MachineState, now: float, why: str) -> None:
        """Change to `new` on `trigger`; `IllegalTransition` unless the table has that row."""
        old = self.state
        if new is old:
            return
        rule = ROWS.get((trigger, old))
        if rule is None or new not in rule.targets:
            raise IllegalTransition(trigger, old, new)
        self.previous_state, self.state = old, new
        if self.on_transition is not None:
            self.on_transition(Transition(old=old, new=new, reason=why, at=now + self.wall_offset))

    def _pick(self, rule: Rule, session: Session | None = None) -> MachineState:
        """The row's target: its only one, or the one its `Pick` chooses from the facts."""
        pick = rule.pick
        if pick is None:
            return rule.targets[0]
        if pick is Pick.REST:
            return self.rest_state()
        if pick is Pick.BEFORE_PAUSE:
            return self._before(self.drive.resume_to)
        if pick is Pick.BEFORE_ESTOP:
            return self._before(self.drive.estop_from)
        if pick is Pick.POLICY:
            stop = self.config.rider_loss.policy is RiderLossPolicy.STOP
            return S.DONE if stop else S.PAUSED
        return handlers.start_target(self, session)

    def rest_state(self) -> MachineState:
        if not self.calibration.complete:
            return S.WARNING_NEEDS_CALIBRATION
        home = self.homed()
        return S.IDLE if home.tilt and home.rotate else S.WARNING_NOT_HOME

    def _before(self, interrupted: MachineState | None) -> MachineState:
        """The interrupted state, or the rest state if it was a motion with nothing to run."""
        to = interrupted or self.rest_state()
        if to in MOTION_STATES and self.drive.controller is None:
            return self.rest_state()
        return to

    # ------------------------------------------------------------------ motion context
    def begin(self, request: CommandRequest, plan: Plan, now: float) -> None:
        """Start a motion: its controller runs in its state; when it finishes, its `on_done`
        says how it ended: the motion's one completion notice."""
        command = plan.command
        if self.action is not None:
            # Only a motion halted by the E-stop can be replaced (Home, Calibrate*): it ended.
            if self.state is S.FAULT_ESTOP:
                ending = Ending(
                    Outcome.FAULT_ESTOP,
                    f"halted by the E-stop and not resumed; replaced by {command.value}",
                    FaultCode.ESTOP.value,
                )
            else:
                ending = Ending(Outcome.STOPPED, f"replaced by {command.value}")
            self.end(ending, now)
        self.clear_motion()
        self.drive = Drive(controller=plan.controller, session_run=plan.session)
        wall = now + self.wall_offset
        self.action = Motion(command, request.transaction_id, request.rider, wall, plan.on_done)
        self.fault = None
        self.watch.warning = None
        self.enter(command, plan.state, now, plan.why or command.value)

    def clear_motion(self) -> None:
        """Abandon the controller (outputs off) and forget the session, where Pause and the
        E-stop came from, and the E-stop latch: a new motion, Stop or a fault starts clean."""
        if self.drive.controller is not None:
            self.drive.controller.abandon()
        self.drive = Drive()
        self.devices.stop_all()

    def pause(self, now: float, why: str, trigger: Trigger = Command.PAUSE) -> None:
        if self.drive.controller is not None:
            self.drive.controller.halt()
        self.drive.resume_to = self.state
        self.go(trigger, now, why)

    def resume(self, now: float) -> None:
        self.watch.warning = None  # whoever resumes has taken over
        drive = self.drive
        after_estop = self.state is S.FAULT_ESTOP
        target = self.target(Command.RESUME)  # before what it reads is cleared
        if after_estop:
            drive.estop_latched = False
            drive.estop_from = None
        else:
            drive.resume_to = None
        if target in MOTION_STATES:
            assert drive.controller is not None  # `Pick.BEFORE_*` chose a motion to run
            drive.controller.resume(now)
        still = after_estop and target is S.PAUSED
        self.enter(
            Command.RESUME, target, now, "Resume after E-stop (still paused)" if still else "Resume"
        )

    def stop(
        self, now: float, why: str, code: str | None = None, trigger: Trigger = Command.STOP
    ) -> None:
        after_estop = self.state is S.FAULT_ESTOP
        self.clear_motion()
        self.fault = None
        self.go(trigger, now, why)
        reason = why + (" after an E-stop" if after_estop else "")
        self.end(Ending(Outcome.STOPPED, reason, code), now)

    def enter_fault(
        self,
        fault: Fault,
        now: float,
        why: str,
        trigger: Trigger = Event.FAULT,
        *,
        moved: bool = True,
    ) -> None:
        """`FAULT_HW`; the axes' references are lost unless nothing moved (`moved=False`: a
        Start refused for its session before any motion began)."""
        self.clear_motion()  # a still-pressed E-stop latches again next cycle
        self.fault = fault
        if moved:
            self.refs.tilt = self.refs.rotate = False
        self.enter(trigger, S.FAULT_HW, now, f"{why}: {fault.message}")
        self.end(Ending(Outcome.FAULT_HW, fault.message, fault.code.value), now)

    # ------------------------------------------------------------------------ completion
    def end(self, ending: Ending, now: float) -> None:
        """The running motion has ended: its one notice (nothing if none is running)."""
        motion, self.action = self.action, None
        if motion is not None:
            self.notify(motion, ending, now)

    def notify(self, motion: Motion, ending: Ending, now: float) -> None:
        self.completions.append(
            Completion(
                machine_id=self.config.machine.id,
                transaction_id=motion.transaction_id,
                command=motion.command.value,
                outcome=ending.outcome,
                code=ending.code,
                reason=ending.reason,
                state=self.state,
                rider=motion.rider,
                started_at=motion.started_at,
                time=now + self.wall_offset,
            )
        )

    def take_completions(self) -> list[Completion]:
        """The notices produced since the last call (the scan loop publishes them)."""
        out, self.completions = self.completions, []
        return out

    def abort(self, now: float, why: str) -> None:
        """The daemon stops: a motion still under way ends `ABORTED` (outputs are safe)."""
        self.changes += 1
        self.end(Ending(Outcome.ABORTED, why), now)

    def homed(self) -> AxesFlags:
        """An axis is home when it has a reference and its home switch is closed now."""
        return AxesFlags(
            tilt=self.refs.tilt and self.devices.tilt.is_home(),
            rotate=self.refs.rotate and self.devices.rotate.is_home(),
        )

    # ----------------------------------------------------------------------------- cycle
    def on_estop(self, now: float) -> None:
        """Called in every cycle the E-stop is active: latch, halt, outputs off."""
        self.changes += 1
        if self.drive.controller is not None:
            self.drive.controller.halt()
        self.devices.stop_all()
        if self.state is not S.FAULT_ESTOP:
            self.drive.estop_from = self.state
            self.drive.estop_latched = True
            self.go(Event.ESTOP, now, "E-stop pressed")

    def update(self, now: float) -> None:
        """Step the active controller; in every other state hold all outputs off."""
        self.changes += 1
        if self.watch.grace_over(now, self.config.rider_loss.grace_s):
            deadman.apply_loss(self, now)
        if self.saving is not None and self.saving.ticket.done:
            calibration.save_done(self, self.saving, now)
        ctl = self.drive.controller
        if self.state not in MOTION_STATES or ctl is None:
            self.devices.stop_all()
            return
        step = ctl.update(now)
        if step is Step.BUSY:
            return
        calibration.verified(self)  # a verification that passed, whatever came after it
        if step is Step.FAULT:
            assert ctl.fault is not None
            command = self.action.command.value if self.action else "motion"
            self.enter_fault(ctl.fault, now, f"{command} failed", Event.MOTION_FAULT)
            return
        motion = self.action
        self.drive.controller = None
        self.devices.stop_all()
        assert motion is not None, "a controller runs only as part of a motion"
        ending = motion.on_done(now)
        if ending is not None:
            self.end(ending, now)

    def enter_calibration(self, values: CalibrationSet, now: float) -> SaveTicket | None:
        """A technician's values (calibration.py): used at once, persisted (the ticket says
        when the write is done, and how); refused while a motion is under way."""
        self.changes += 1
        return calibration.enter(self, values, now)

    def duplicate_id(self, others: tuple[str, ...], own: str, now: float) -> None:
        """Other sessions hold this machine's id (`others`, empty: alone again). Met: motion
        stops in this cycle (FAULT_HW, DUPLICATE_ID); alone again: the fault stays (it
        latches like any fault) and commands are taken again; nothing moves by itself."""
        self.changes += 1
        was, self.duplicate_of = self.duplicate_of, others
        mid = self.config.machine.id
        if others:
            self.external_fault(
                Fault(
                    code=FaultCode.DUPLICATE_ID,
                    message=f"machine id {mid} is held by this session ({own}) and by"
                    f" {', '.join(others)}: motion stopped, commands refused until one is alone",
                ),
                now,
            )
        elif was and self.fault is not None and self.fault.code is FaultCode.DUPLICATE_ID:
            self.fault = Fault(
                code=FaultCode.DUPLICATE_ID,
                message=f"machine id {mid} was also held by {', '.join(was)}; alone again:"
                " Home (or Calibrate) to go on",
            )

    def external_fault(self, fault: Fault, now: float) -> None:
        """A fault raised outside the controllers (watchdog, supervisor, loop exception)."""
        self.changes += 1
        self.enter_fault(fault, now, fault.code.value)

    def motion(self) -> Controller | None:
        """The controller that owns an axis now (running, paused or held by an E-stop)."""
        ctl = self.drive.controller
        return ctl.active() if ctl is not None else None

    def is_moving(self) -> bool:
        """Motion is under way or can be resumed (paused, or halted by a released E-stop)."""
        return self.state in MOTION_STATES or self.drive.controller is not None

    def at_rest(self) -> bool:
        """Nothing pending that `update` acts on by itself as time passes (a controller, a
        calibration being saved, a lost Rider's grace period) or that the loop still has to
        take (a completion notice)."""
        return (
            self.drive.controller is None
            and self.saving is None
            and self.watch.gone_at is None
            and not self.completions
        )

    # ------------------------------------------------------------------- the Rider deadman
    def rider_lost(self, now: float) -> bool:
        """The controlling Rider's token went (deadman.py); True if the policy acted now."""
        self.changes += 1
        return deadman.lost(self, now)

    def rider_heartbeat(self, at: float | None, now: float) -> Verdict:
        """Deadman check, once per cycle: `at` is when the controlling Rider's heartbeat last
        arrived (None: never); what the deadman found (deadman.py)."""
        verdict = deadman.heard(self, at, now)
        if verdict is not Verdict.QUIET:
            self.changes += 1
        return verdict

    def rider_back(self) -> None:
        """The controlling Rider's token is back (within the grace period nothing happened)."""
        self.changes += 1
        self.watch.back()

    # ---------------------------------------------------------------------------- status
    def session_progress(self) -> SessionProgress | None:
        run = self.drive.session_run
        return run.progress() if run is not None else None

    def snapshot(self) -> Snapshot:
        """The machine now, as one value (snapshot.py); taken once per full scan cycle."""
        return snapshot_of(self)
