"""`StateMachine`: the machine's states, run by the table. Pure logic: no IO, no clock, time in.

It keeps the state and changes it only through `enter`, which refuses any change the table
does not have (`IllegalTransition`); where a trigger leads is the table's row, and the row's
`Pick` judged on the machine's `Facts` (guards.py). Its parts own the rest: the motion context
(drive, action, notices: context.py), the Rider watch (deadman.py), the calibration keeper
(calibration.py). A command comes in through `handle`, which asks its handler once
(handlers.py) and carries out what it returns; the scan cycle through `on_estop` and `update`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Concatenate, ParamSpec, TypeVar

from ride_machine.schema.calibration import CalibrationSet
from ride_machine.schema.commands import (
    DEFAULT_SESSION,
    REST_STATES,
    CheckResult,
    Command,
    CommandRequest,
    Reply,
    Session,
    StartRequest,
)
from ride_machine.schema.completion import Outcome
from ride_machine.schema.status import MOTION_STATES, Fault, FaultCode, MachineState
from ride_machine.service.config.model import LiveConfig, RiderLossPolicy
from ride_machine.service.core.commands.admission import admit
from ride_machine.service.core.motion.base import Controller, Step
from ride_machine.service.core.motion.devices import Calibration, Devices
from ride_machine.service.errors import MachineError

from .calibration import CalibrationKeeper, OnCalibrated
from .context import Ending, Motion, MotionContext, Plan, never
from .deadman import RiderWatch, Verdict
from .guards import Facts, choose, refusal, session_problem
from .handlers import ACTIONS, Check, Order, Refusal
from .snapshot import Snapshot
from .table import (
    ACCEPTS,
    HANDLING,
    ONLY,
    POWER_UP,
    ROWS,
    IllegalTransition,
    Occurrence,
    Transition,
    Trigger,
)

if TYPE_CHECKING:  # types only: the state machine does no IO
    from ride_machine.service.core.storage.persist import SaveTicket, StorageHealth

S = MachineState
C = Command
P = ParamSpec("P")
R = TypeVar("R")


def acts(
    method: Callable[Concatenate[StateMachine, P], R],
) -> Callable[Concatenate[StateMachine, P], R]:
    """The one place a change is counted: a method that may change what the machine shows
    counts each call in `changes`, first, whatever it then does (the quiet cycles compare it)."""

    @functools.wraps(method)
    def counted(self: StateMachine, /, *args: P.args, **kwargs: P.kwargs) -> R:
        self.changes += 1
        return method(self, *args, **kwargs)

    return counted


class StateMachine:
    """Commands in, a state and desired outputs out; `update(now)` once per scan cycle."""

    def __init__(
        self,
        devices: Devices,
        live: LiveConfig,
        calibration: Calibration | None = None,
        on_calibrated: OnCalibrated | None = None,
        storage: StorageHealth | None = None,
        on_transition: Callable[[Transition], None] | None = None,
        wall_offset: float = 0.0,
        warnings: list[str] | None = None,
    ) -> None:
        """`live`: the running config (online parameters change it between cycles): read,
        never kept; `storage`: what could not be written to the data dir (its warnings are
        part of the status); `warnings`: from start-up (a file that could not be read)."""
        self.devices = devices
        self.live = live
        self.storage = storage
        self.on_transition = on_transition
        self.wall_offset = wall_offset
        self.warnings = warnings if warnings is not None else []
        self.context = MotionContext(devices, live)
        self.watch = RiderWatch()
        """The controlling Rider, as the deadman sees it."""
        self.keeper = CalibrationKeeper(calibration or Calibration(), devices, on_calibrated)
        self.previous_state: MachineState | None = None
        self.fault: Fault | None = None
        self.duplicate_of: tuple[str, ...] = ()
        """Other sessions holding this machine's id (the bus watches `holder/<zid>`)."""
        self.changes = 0
        """Calls that may have changed the machine (`acts`): the quiet cycles compare it."""
        self.state = choose(POWER_UP, self.facts())  # never assumed home
        if self.state not in POWER_UP.targets:
            raise IllegalTransition(Occurrence.POWER_UP, None, self.state)
        devices.stop_all()

    # ------------------------------------------------------------------------ the table
    def facts(self, session: Session | None = None) -> Facts:
        """What the table's guards read now (`session`: the one Start's checks judge)."""
        keeper, drive = self.keeper, self.context.drive
        config = self.live.current
        return Facts(
            uncalibrated=keeper.uncalibrated(),
            not_home=keeper.not_home(),
            resume_to=drive.resume_to,
            estop_from=drive.estop_from,
            runnable=drive.controller is not None,
            stop_on_loss=config.rider_loss.policy is RiderLossPolicy.STOP,
            estop=self.devices.safety.is_estop_active(),
            held_by=self.duplicate_of,
            session=session,
            bad_session=None if session is None else session_problem(session, config.tilt),
        )

    def target(self, trigger: Trigger, facts: Facts | None = None) -> MachineState:
        """Where `trigger` leads from the current state: its row's target (chosen by the row's
        `Pick` where it has several), else the state itself; a trigger without a row here is
        refused unless it leads only here (an E-stop or a fault met again changes nothing)."""
        state = self.state
        rule = ROWS.get((trigger, state))
        if rule is None and ONLY.get(trigger) is not state:
            raise IllegalTransition(trigger, state, None)
        if rule is None or not rule.targets:
            return state
        chosen = choose(rule, facts or self.facts())
        if chosen not in rule.targets:
            raise IllegalTransition(trigger, state, chosen)
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

    # ------------------------------------------------------------------------- commands
    @acts
    def handle(self, command: Command, request: CommandRequest, now: float) -> Reply:
        """Act on one command and say what happened: its handler says what to do (the one
        call into handlers.py), the machine does it; refusals change nothing but the reply."""
        stamp = now + self.wall_offset
        handling = HANDLING[command]
        config = self.live.current
        try:
            if handling.moves:
                admit(command, request, stamp, config.bus.clock_margin_s)
            asked = request.session if isinstance(request, StartRequest) else None
            facts = self.facts(asked or DEFAULT_SESSION if command is C.START else None)
            refused = refusal(ACCEPTS[command], self.state, facts, config.machine.id)
            if refused is not None and not handling.read_only:
                raise refused
            order = ACTIONS[command](self, facts)
            result = self._carry_out(command, order, request, facts, now)
        except MachineError as exc:
            return Reply.failure(
                exc.to_error(),
                transaction_id=request.transaction_id,
                command=command.value,
                timecode=stamp,
                state=self.state,
                request_timecode=request.timecode,
            )
        if handling.moves:  # the command itself is a sign of life
            self.watch.take(request.rider, now)
        return Reply(
            transaction_id=request.transaction_id,
            command=command._value_,
            timecode=stamp,
            request_timecode=request.timecode,
            success=True,
            code=handling.reply,
            state=self.state,
            result=result,
        )

    def _carry_out(
        self, command: Command, order: Order, request: CommandRequest, facts: Facts, now: float
    ) -> CheckResult | None:
        """What a handler asked for, done: a check answered, a Start refused, a motion begun,
        or the command's own transition (Pause, Resume, Stop)."""
        wall = now + self.wall_offset
        if isinstance(order, Check):
            if order.why is not None:
                self.go(command, now, order.why)
            return order.result
        target = self.target(command, facts)
        if isinstance(order, Refusal):
            if order.fault is not None:
                self.external_fault(order.fault, now, order.why, C.START, moved=False)
            else:
                self.enter(C.START, target, now, order.why)
            error = order.error
            ending = Ending(order.outcome, error.message, error.code.value)
            motion = Motion(C.START, request.transaction_id, request.rider, wall, never)
            self.context.notify(motion, ending, self.state, wall)  # though nothing began
            raise error
        if isinstance(order, Plan):
            motion = Motion(command, request.transaction_id, request.rider, wall, order.on_done)
            self.context.begin(order, motion, self.state, wall)
            self.fault = self.watch.warning = None
            self.enter(command, target, now, order.why or command.value)
        elif order is C.PAUSE:
            self.pause(now, "Pause")
        elif order is C.RESUME:
            self.watch.warning = None  # whoever resumes has taken over
            after_estop = self.state is S.FAULT_ESTOP
            self.context.resume(after_estop, target in MOTION_STATES, now)
            still = after_estop and target is S.PAUSED
            self.enter(
                command, target, now, "Resume after E-stop (still paused)" if still else "Resume"
            )
        else:
            self.stop(now, "Stop")
        return None

    def pause(self, now: float, why: str, trigger: Trigger = C.PAUSE) -> None:
        self.context.pause(self.state)
        self.go(trigger, now, why)

    def stop(
        self, now: float, why: str, code: str | None = None, trigger: Trigger = C.STOP
    ) -> None:
        after_estop = self.state is S.FAULT_ESTOP
        self.context.clear()
        self.fault = None
        self.go(trigger, now, why)
        reason = why + (" after an E-stop" if after_estop else "")
        self.context.end(Ending(Outcome.STOPPED, reason, code), self.state, now + self.wall_offset)

    @acts
    def external_fault(
        self,
        fault: Fault,
        now: float,
        why: str | None = None,
        trigger: Trigger = Occurrence.FAULT,
        *,
        moved: bool = True,
    ) -> None:
        """`FAULT_HW`: raised outside the controllers (watchdog, supervisor, loop exception),
        or by a motion (`Occurrence.MOTION_FAULT`). The axes' references are lost unless nothing
        moved (`moved=False`: a Start refused for its session before any motion began)."""
        self.context.clear()  # a still-pressed E-stop latches again next cycle
        self.fault = fault
        if moved:
            self.keeper.lose_references()
        self.enter(trigger, S.FAULT_HW, now, f"{why or fault.code.value}: {fault.message}")
        ending = Ending(Outcome.FAULT_HW, fault.message, fault.code.value)
        self.context.end(ending, self.state, now + self.wall_offset)

    @acts
    def abort(self, now: float, why: str) -> None:
        """The daemon stops: a motion still under way ends `ABORTED` (outputs are safe)."""
        self.context.end(Ending(Outcome.ABORTED, why), self.state, now + self.wall_offset)

    # ----------------------------------------------------------------------------- cycle
    @acts
    def on_estop(self, now: float) -> None:
        """Called in every cycle the E-stop is active: latch, halt, outputs off."""
        latched = self.state is S.FAULT_ESTOP
        self.context.estop(None if latched else self.state)
        if not latched:
            self.go(Occurrence.ESTOP, now, "E-stop pressed")

    @acts
    def update(self, now: float) -> None:
        """Step the active controller (in every other state hold all outputs off), then end a
        calibration whose write has ended."""
        if self.watch.grace_over(now, self.live.current.rider_loss.grace_s):
            self._rider_gone(now)
        ctl, context = self.context.drive.controller, self.context
        if self.state not in MOTION_STATES or ctl is None:
            self.devices.stop_all()
        elif (step := ctl.update(now)) is not Step.BUSY:
            self.keeper.verified()  # a verification that passed, whatever came after it
            motion = context.action
            if step is Step.FAULT:
                assert ctl.fault is not None
                why = f"{motion.command.value if motion else 'motion'} failed"
                self.external_fault(ctl.fault, now, why, Occurrence.MOTION_FAULT)
                return
            assert motion is not None, "a controller runs only as part of a motion"
            context.drive.controller = None
            self.devices.stop_all()
            ending = motion.on_done(now)
            if ending is not None:
                context.end(ending, self.state, now + self.wall_offset)
        if self.keeper.written():
            saved = self.keeper.saved()
            if self.state is S.CALIBRATING and context.drive.controller is None:
                self.go(Occurrence.SAVED, now, saved.why)
            if context.action is not None and context.action is saved.motion:
                context.end(saved.ending, self.state, now + self.wall_offset)

    @acts
    def enter_calibration(self, values: CalibrationSet, now: float) -> SaveTicket | None:
        """A technician's values (the keeper's `entered`): used at once, persisted (the
        ticket says when the write is done, and how); refused while a motion is under way."""
        busy = self.is_moving() or self.context.action is not None
        wall = now + self.wall_offset
        ticket = self.keeper.entered(values, self.live.current, wall, self.state, busy)
        if self.state in REST_STATES and self.state is not S.DONE:
            self.go(Occurrence.CALIBRATION_ENTERED, now, "calibration entered by hand")
        return ticket

    @acts
    def duplicate_id(self, others: tuple[str, ...], own: str, now: float) -> None:
        """Other sessions hold this machine's id (`others`, empty: alone again). Met: motion
        stops in this cycle (FAULT_HW, DUPLICATE_ID); alone again: the fault stays (it
        latches like any fault) and commands are taken again; nothing moves by itself."""
        was, self.duplicate_of = self.duplicate_of, others
        mid = self.live.current.machine.id
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

    # ------------------------------------------------------------------- the Rider deadman
    @acts
    def rider_lost(self, now: float) -> bool:
        """The controlling Rider's token went: the rider-loss policy applies now, or after
        the grace period if it does not come back; True if it acted now."""
        if self.watch.gone(now, self.live.current.rider_loss.grace_s):
            return self._rider_gone(now)
        return False

    def rider_heartbeat(self, at: float | None, now: float) -> Verdict:
        """Deadman check, once per cycle: `at` is when the controlling Rider's heartbeat last
        arrived (None: never). Silent for `rider_loss.timeout_s` → LOST (the policy applies);
        a heartbeat after a loss → BACK (a paused ride stays paused)."""
        verdict = self.watch.heard(at, now, self.live.current.rider_loss.timeout_s)
        if verdict is Verdict.LOST:
            self.rider_lost(now)
        elif verdict is Verdict.BACK:
            self.rider_back()
        return verdict

    @acts
    def rider_back(self) -> None:
        """The controlling Rider is back (within the grace period nothing happened)."""
        self.watch.back()

    def _rider_gone(self, now: float) -> bool:
        """The watch judged the Rider lost: the policy, now; True if it paused or stopped."""
        if not self.watch.loss(self.state, self.live.current.rider_loss.policy):
            return False
        if self.target(Occurrence.RIDER_LOST) is S.PAUSED:
            self.pause(now, "Rider lost", Occurrence.RIDER_LOST)
        else:
            self.stop(now, "Rider lost", "RIDER_LOST", Occurrence.RIDER_LOST)
        return True

    # -------------------------------------------------------- what the loop reads of it
    @property
    def calibration(self) -> Calibration:
        return self.keeper.calibration

    @property
    def action(self) -> Motion | None:
        return self.context.action

    @property
    def estop_latched(self) -> bool:
        return self.context.drive.estop_latched

    @property
    def controller_rider(self) -> str | None:
        return self.watch.id

    def motion(self) -> Controller | None:
        """The controller that owns an axis now (running, paused or held by an E-stop)."""
        return self.context.active()

    def is_moving(self) -> bool:
        """Motion is under way or can be resumed (paused, or halted by a released E-stop)."""
        return self.state in MOTION_STATES or self.context.drive.controller is not None

    def at_rest(self) -> bool:
        """Nothing pending that `update` acts on by itself as time passes (a controller, a
        calibration being saved, a lost Rider's grace period) or that the loop still has to
        take (a completion notice)."""
        return self.context.at_rest() and self.keeper.saving is None and self.watch.gone_at is None

    def snapshot(self) -> Snapshot:
        """The machine now, as one value; a full cycle takes one (the quiet ones rely on
        `changes`)."""
        drive, watch, devices, refs = self.context.drive, self.watch, self.devices, self.keeper.refs
        run, storage = drive.session_run, self.storage
        return Snapshot(
            state=self.state,
            previous_state=self.previous_state,
            fault=self.fault,
            estop_active=devices.safety.is_estop_active(),
            estop_latched=drive.estop_latched,
            calibration=self.keeper.calibration,
            home_tilt=refs.tilt and devices.tilt.is_home(),
            home_rotate=refs.rotate and devices.rotate.is_home(),
            session=run,
            step=run.index if run is not None else None,
            revolutions=run.revolutions_done() if run is not None else None,
            motion=self.context.action,
            rider_connected=watch.connected,
            warnings=tuple(self.warnings),
            rider_warning=watch.warning,
            storage=storage.version if storage is not None else 0,
            rider=watch.id,
            resume_to=drive.resume_to,
            estop_from=drive.estop_from,
            duplicate_of=self.duplicate_of,
        )
