"""`ControlAPI`: the machine's state machine. Pure logic: no IO, no clock, time comes in.

Its behaviour is data (at the end of this module): `TABLE` lists every `(trigger, states) →
targets` row, for the commands and for the events (E-stop, a motion's end, a fault, a lost
Rider); `HANDLING` gives each command its one handler and reply. The command guard reads them,
and the README's state table and docs/states.md are generated from them
(`python -m service.core.control_doc`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

from schema.calibration import CalibrationSet
from schema.commands import (
    ALLOWED_STATES,
    DEFAULT_SESSION,
    REST_STATES,
    CheckResult,
    Command,
    CommandRequest,
    Reply,
    ReplyCode,
    RotateStep,
    Session,
    StartRequest,
    TiltStep,
)
from schema.completion import Completion
from schema.completion import Outcome as End
from schema.errors import ErrorCode
from schema.status import (
    MOTION_STATES,
    AxesFlags,
    EstopInfo,
    Fault,
    FaultCode,
    MachineState,
    MotionRef,
    SessionProgress,
)
from service.config.model import LiveConfig, MachineConfig, RiderLossPolicy
from service.core.admission import admit
from service.core.calibrate import RotateCalibrate, TiltCalibrate
from service.core.controllers import SessionRun
from service.core.devices import Calibration, Devices
from service.core.homing import RotateHome, TiltHome
from service.core.manual import manual_calibration
from service.core.motion import Chain, Controller, Outcome
from service.errors import (
    DuplicateId,
    EstopActive,
    InvalidSession,
    MachineError,
    NotCalibrated,
    NotHome,
    WrongState,
)

if TYPE_CHECKING:  # types only: the state machine does no IO
    from service.core.persist import SaveTicket, StorageHealth

S = MachineState


def allowed_states(command: Command) -> frozenset[MachineState]:
    """The states in which `command` is accepted (E-stop released), as the table says."""
    return _ACCEPTED[command]


class Event(StrEnum):
    """What changes the state besides a command: the table's rows that no Rider sends."""

    POWER_UP = "power-up"
    ESTOP = "E-stop pressed"
    MOTION_DONE = "motion done"
    MOTION_FAULT = "motion fault"
    SAVED = "calibration saved"
    RIDER_LOST = "Rider lost"
    FAULT = "fault"
    CALIBRATION_ENTERED = "calibration entered"


Handler = Callable[["ControlAPI", CommandRequest, float], "CheckResult | None"]
"""A command's action: it changes the state (or raises a `MachineError`) and may return a
check result for the reply."""


@dataclass(frozen=True, slots=True)
class Rule:
    """One row of the machine's behaviour: `trigger` in any of `sources` leads to one of
    `targets` or leaves the state as it is (a refused command always does)."""

    trigger: Command | Event
    sources: frozenset[MachineState]
    targets: tuple[MachineState, ...]
    does: str
    """The action in the docs' words, and how the target is chosen when there are several."""


@dataclass(frozen=True, slots=True)
class Handling:
    """How a command is acted on: its handler and the reply it earns."""

    action: Handler
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


@dataclass(frozen=True, slots=True)
class Ending:
    """How a motion ended, before it becomes a `Completion` notice."""

    outcome: End
    reason: str
    code: str | None = None


OnDone = Callable[[float], "Ending | None"]
"""What to do when a motion's controller finishes, bound when the motion begins: settle the
state and say how it ended (None: not ended yet, e.g. a calibration still being saved)."""


def _never(now: float) -> Ending | None:
    """The `on_done` of a notice that ends a command before any motion began."""
    raise AssertionError("no controller runs for a refused Start")


@dataclass(frozen=True, slots=True)
class Plan:
    """What a motion command begins: its controller runs in `state`, and `on_done` (bound
    now) settles the state when it finishes and says how the motion ended."""

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
class _Drive:
    """What a motion leaves behind until `_clear_motion()` resets it in one go."""

    controller: Controller | None = None
    """Drives the axes: running, paused or held by an E-stop (None once finished)."""
    session_run: SessionRun | None = None
    """The session's progress; kept after it ends so the status shows how far it went."""
    resume_to: MachineState | None = None
    """The state Pause interrupted."""
    estop_from: MachineState | None = None
    """The state the E-stop interrupted."""
    estop_latched: bool = False


@dataclass(slots=True)
class _RiderWatch:
    """The controlling Rider (sender of the last moving command) as the deadman sees it."""

    id: str | None = None
    connected: bool = False
    gone_at: float | None = None
    """When its token went (the grace period runs from here); None: not gone."""
    heard_at: float = 0.0
    """Its last sign of life: the command itself, then each heartbeat."""
    warning: str | None = None

    def gone(self, now: float, grace_s: float) -> bool:
        """Its token went: True if the rider-loss policy applies now (no grace period)."""
        self.connected = False
        if grace_s > 0:
            self.gone_at = now
            return False
        return True

    def back(self) -> None:
        self.connected = True
        self.gone_at = None

    def silent(self, at: float | None, now: float, timeout_s: float) -> bool:
        """A heartbeat last arrived at `at` (None: never); True once silent past `timeout_s`.
        A heartbeat after a loss brings it back (nothing moves by itself)."""
        if at is not None and at > self.heard_at:
            self.heard_at = at
            if not self.connected:
                self.back()
        return self.connected and now - self.heard_at > timeout_s


@dataclass(frozen=True, slots=True)
class _Saving:
    """A calibration's write under way, and the motion whose notice waits for it."""

    ticket: SaveTicket
    motion: Motion | None


@dataclass
class _Refs:
    """Which axes have a position reference since power-up or the last hardware fault."""

    tilt: bool = False
    rotate: bool = False


@dataclass
class ControlAPI:
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

    @property
    def config(self) -> MachineConfig:
        return self.live.current

    def __post_init__(self) -> None:
        self.devices.tilt.calibration = self.calibration.tilt
        self.refs = _Refs()
        self.state = self._rest_state()  # power-up: never assumed home
        self.previous_state: MachineState | None = None
        self.fault: Fault | None = None
        self._drive = _Drive()
        self._rider = _RiderWatch()
        self.duplicate_of: tuple[str, ...] = ()
        """Other sessions holding this machine's id (the bus watches `holder/<zid>`)."""
        self.action: Motion | None = None
        """The motion command whose completion notice is still due (running, paused,
        E-stopped), like a ROS 2 action goal; `motion()` is the controller driving it."""
        self.completions: list[Completion] = []
        """Notices produced and not yet taken by the scan loop (`take_completions`)."""
        self._saving: _Saving | None = None
        self.save_ticket: SaveTicket | None = None
        """The write of the calibration in use (None: nothing to write it to, or not yet)."""
        self.devices.stop_all()

    # The motion context and the controlling Rider, read-only from outside.
    @property
    def controller(self) -> Controller | None:
        return self._drive.controller

    @property
    def session_run(self) -> SessionRun | None:
        return self._drive.session_run

    @property
    def estop_latched(self) -> bool:
        return self._drive.estop_latched

    @property
    def controller_rider(self) -> str | None:
        return self._rider.id

    @property
    def rider_connected(self) -> bool:
        return self._rider.connected

    @property
    def rider_warning(self) -> str | None:
        return self._rider.warning

    # ------------------------------------------------------------------------- commands
    def handle(self, command: Command, request: CommandRequest, now: float) -> Reply:
        """Act on one command and say what happened; refusals change nothing but the reply."""
        stamp = now + self.wall_offset
        handling = HANDLING[command]
        try:
            if handling.moves:
                admit(command, request, stamp, self.config.bus.clock_margin_s)
            if not handling.read_only:
                self._guard(command)
            result = handling.action(self, request, now)
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
            self._rider = _RiderWatch(request.rider, request.rider is not None, heard_at=now)
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

    def _guard(self, command: Command) -> None:
        """Refuse a command this machine cannot take now: id held twice, E-stop, state."""
        if self.duplicate_of:
            raise DuplicateId(
                f"{command.value} refused: machine id {self.config.machine.id} is also held by"
                f" session {', '.join(self.duplicate_of)}; nothing is taken until one of the"
                " two daemons is stopped or given another id"
            )
        if self.devices.safety.is_estop_active():
            raise EstopActive(
                f"{command.value} refused: the E-stop is active; release it, then Resume,"
                " Home or Stop"
            )
        if self.state not in _ACCEPTED[command]:
            raise WrongState(
                f"{command.value} is not accepted in state {self.state};"
                f" accepted in: {_ACCEPTED_TEXT[command]}"
            )

    # One handler per command (the table's `action`).
    def _calibrate_tilt(self, request: CommandRequest, now: float) -> None:
        tilt = TiltCalibrate(self.devices.tilt, self.config.tilt)
        done = self._tilt_calibrated
        plan = Plan(Command.CALIBRATE_TILT, S.CALIBRATING, tilt, lambda at: done(tilt, at))
        self.begin(request, plan, now)

    def _calibrate_rotate(self, request: CommandRequest, now: float) -> None:
        rotate = RotateCalibrate(self.devices.rotate, self.config.rotate)
        chain, done = Chain([self._tilt_home, lambda: rotate]), self._rotate_calibrated
        plan = Plan(Command.CALIBRATE_ROTATE, S.CALIBRATING, chain, lambda at: done(rotate, at))
        self.begin(request, plan, now)

    def _home(self, request: CommandRequest, now: float) -> None:
        home = Chain([self._tilt_home, self._rotate_home])
        self.begin(request, Plan(Command.HOME, S.HOMING, home, self._homed), now)

    def _tilt_home(self) -> Controller:
        return TiltHome(self.devices.tilt, self.config.tilt)

    def _rotate_home(self) -> Controller:
        cal = self.calibration.rotate
        speed = cal.speed_dps if cal is not None else None
        return RotateHome(self.devices.rotate, self.config.rotate, speed)

    def _start(self, request: CommandRequest, now: float) -> None:
        """The seed's Session(): CheckCalibrate, CheckHome, CheckSession, then run. A check
        that fails sets its state, then ends this Start with a notice (the seed's "send
        WARNING…, stop session, send DONE"), and the reply says why."""
        session = request.session if isinstance(request, StartRequest) else None
        session = session or DEFAULT_SESSION
        refusal = self._start_refusal(session, now)
        if refusal is not None:
            outcome, error = refusal
            wall = now + self.wall_offset
            motion = Motion(Command.START, request.transaction_id, request.rider, wall, _never)
            self._notify(motion, Ending(outcome, error.message, error.code.value), now)
            raise error
        assert self.calibration.rotate is not None  # checked complete above
        run = SessionRun(session, self.devices, self.config, self.calibration.rotate)
        why = f"Start session {session.name!r}"
        self.begin(request, Plan(Command.START, S.RUNNING, run, self._session_done, why, run), now)

    def _start_refusal(self, session: Session, now: float) -> tuple[End, MachineError] | None:
        """The first of Start's checks that fails, with the state it sets; None: all pass."""
        if not self.calibration.complete:
            missing = [a for a in ("tilt", "rotate") if getattr(self.calibration, a) is None]
            self._set_state(S.WARNING_NEEDS_CALIBRATION, now, "Start: not calibrated")
            return End.REFUSED, NotCalibrated(
                f"Start refused: {' and '.join(missing)} not calibrated"
            )
        home = self.homed()
        if not (home.tilt and home.rotate):
            missing = [a for a in ("tilt", "rotate") if not getattr(home, a)]
            self._set_state(S.WARNING_NOT_HOME, now, "Start: not home")
            return End.REFUSED, NotHome(
                f"Start refused: {' and '.join(missing)} not home; send Home first"
            )
        problem = self._session_problem(session)
        if problem is None:
            return None
        path, message = problem
        fault = Fault(code=FaultCode.INVALID_SESSION, message=message)
        self._enter_fault(fault, now, "Start: bad session")
        return End.FAULT_HW, InvalidSession(message, path)

    def _session_problem(self, session: Session) -> tuple[str, str] | None:
        """The first step this machine cannot do, as (JSON pointer, message)."""
        lo, hi = self.config.tilt.min_deg, self.config.tilt.max_deg
        for i, step in enumerate(session.steps):
            if isinstance(step, TiltStep) and not lo <= step.degrees <= hi:
                return (
                    f"/session/steps/{i}/degrees",
                    f"step {i}: tilt {step.degrees:g}° is outside this machine's range"
                    f" {lo:g}..{hi:g}°",
                )
            if isinstance(step, RotateStep) and step.revolutions < 1:
                return (f"/session/steps/{i}/revolutions", f"step {i}: revolutions must be ≥ 1")
        return None

    def _pause_command(self, request: CommandRequest, now: float) -> None:
        self._pause(now, "Pause")

    def _resume_command(self, request: CommandRequest, now: float) -> None:
        self._resume(now)

    def _stop_command(self, request: CommandRequest, now: float) -> None:
        self._stop(now, "Stop")

    def _check_calibration(self, request: CommandRequest, now: float) -> CheckResult:
        cal = self.calibration
        result = CheckResult(
            ok=cal.complete, tilt=cal.tilt is not None, rotate=cal.rotate is not None
        )
        if self.state in REST_STATES:
            if not result.ok:
                self._set_state(S.WARNING_NEEDS_CALIBRATION, now, "CheckCalibration failed")
            elif self.state is S.WARNING_NEEDS_CALIBRATION:
                self._set_state(self._rest_state(), now, "CheckCalibration passed")
        return result

    def _check_home(self, request: CommandRequest, now: float) -> CheckResult:
        home = self.homed()
        result = CheckResult(ok=home.tilt and home.rotate, tilt=home.tilt, rotate=home.rotate)
        if self.state in REST_STATES:
            # Needing calibration is the bigger problem: that warning is not hidden.
            if not result.ok and self.state is not S.WARNING_NEEDS_CALIBRATION:
                self._set_state(S.WARNING_NOT_HOME, now, "CheckHome failed")
            elif self.state is S.WARNING_NOT_HOME:
                self._set_state(self._rest_state(), now, "CheckHome passed")
        return result

    # ------------------------------------------------------------------ motion context
    def begin(self, request: CommandRequest, plan: Plan, now: float) -> None:
        """Start a motion: its controller runs in its state; when it finishes, its `on_done`
        settles the state and says how it ended: the motion's one completion notice."""
        command = plan.command
        if self.action is not None:
            # Only a motion halted by the E-stop can be replaced (Home, Calibrate*): it ended.
            if self.state is S.FAULT_ESTOP:
                ending = Ending(
                    End.FAULT_ESTOP,
                    f"halted by the E-stop and not resumed; replaced by {command.value}",
                    FaultCode.ESTOP.value,
                )
            else:
                ending = Ending(End.STOPPED, f"replaced by {command.value}")
            self._end(ending, now)
        self._clear_motion()
        self._drive = _Drive(controller=plan.controller, session_run=plan.session)
        wall = now + self.wall_offset
        self.action = Motion(command, request.transaction_id, request.rider, wall, plan.on_done)
        self.fault = None
        self._rider.warning = None
        self._set_state(plan.state, now, plan.why or command.value)

    def _clear_motion(self) -> None:
        """Abandon the controller (outputs off) and forget the session, where Pause and the
        E-stop came from, and the E-stop latch: a new motion, Stop or a fault starts clean."""
        if self._drive.controller is not None:
            self._drive.controller.abandon()
        self._drive = _Drive()
        self.devices.stop_all()

    def _pause(self, now: float, why: str) -> None:
        if self._drive.controller is not None:
            self._drive.controller.halt()
        self._drive.resume_to = self.state
        self._set_state(S.PAUSED, now, why)

    def _resume(self, now: float) -> None:
        self._rider.warning = None  # whoever resumes has taken over
        drive = self._drive
        if self.state is S.FAULT_ESTOP:
            target = drive.estop_from or self._rest_state()
            drive.estop_latched = False
            drive.estop_from = None
            if target is S.PAUSED:
                self._set_state(S.PAUSED, now, "Resume after E-stop (still paused)")
                return
        else:
            target = drive.resume_to or self._rest_state()
            drive.resume_to = None
        if target in MOTION_STATES and drive.controller is not None:
            drive.controller.resume(now)
        elif target in MOTION_STATES:
            target = self._rest_state()
        self._set_state(target, now, "Resume")

    def _stop(self, now: float, why: str, code: str | None = None) -> None:
        after_estop = self.state is S.FAULT_ESTOP
        self._clear_motion()
        self.fault = None
        self._set_state(S.DONE, now, why)
        self._end(Ending(End.STOPPED, why + (" after an E-stop" if after_estop else ""), code), now)

    def _enter_fault(self, fault: Fault, now: float, why: str) -> None:
        self._clear_motion()  # a still-pressed E-stop latches again next cycle
        self.fault = fault
        self.refs.tilt = self.refs.rotate = False
        self._set_state(S.FAULT_HW, now, f"{why}: {fault.message}")
        self._end(Ending(End.FAULT_HW, fault.message, fault.code.value), now)

    # ------------------------------------------------------------------------ completion
    def _end(self, ending: Ending, now: float) -> None:
        """The running motion has ended: its one notice (nothing if none is running)."""
        motion, self.action = self.action, None
        if motion is not None:
            self._notify(motion, ending, now)

    def _notify(self, motion: Motion, ending: Ending, now: float) -> None:
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
        self._end(Ending(End.ABORTED, why), now)

    def homed(self) -> AxesFlags:
        """An axis is home when it has a reference and its home switch is closed now."""
        return AxesFlags(
            tilt=self.refs.tilt and self.devices.tilt.is_home(),
            rotate=self.refs.rotate and self.devices.rotate.is_home(),
        )

    def _rest_state(self) -> MachineState:
        if not self.calibration.complete:
            return S.WARNING_NEEDS_CALIBRATION
        home = self.homed()
        return S.IDLE if home.tilt and home.rotate else S.WARNING_NOT_HOME

    # ----------------------------------------------------------------------------- cycle
    def on_estop(self, now: float) -> None:
        """Called in every cycle the E-stop is active: latch, halt, outputs off."""
        if self._drive.controller is not None:
            self._drive.controller.halt()
        self.devices.stop_all()
        if self.state is not S.FAULT_ESTOP:
            self._drive.estop_from = self.state
            self._drive.estop_latched = True
            self._set_state(S.FAULT_ESTOP, now, "E-stop pressed")

    def update(self, now: float) -> None:
        """Step the active controller; in every other state hold all outputs off."""
        gone = self._rider.gone_at
        if gone is not None and now - gone >= self.config.rider_loss.grace_s:
            self._apply_rider_loss(now)
        if self._saving is not None and self._saving.ticket.done:
            self._save_done(self._saving, now)
        ctl = self._drive.controller
        if self.state not in MOTION_STATES or ctl is None:
            self.devices.stop_all()
            return
        outcome = ctl.update(now)
        if outcome is Outcome.BUSY:
            return
        if outcome is Outcome.FAULT:
            assert ctl.fault is not None
            command = self.action.command.value if self.action else "motion"
            self._enter_fault(ctl.fault, now, f"{command} failed")
            return
        motion = self.action
        self._drive.controller = None
        self.devices.stop_all()
        assert motion is not None, "a controller runs only as part of a motion"
        ending = motion.on_done(now)
        if ending is not None:
            self._end(ending, now)

    # The `on_done` actions, bound when each motion begins.
    def _session_done(self, now: float) -> Ending:
        self._set_state(S.DONE, now, "session complete")
        return Ending(End.DONE, "session complete")

    def _homed(self, now: float) -> Ending:
        self.refs.tilt = self.refs.rotate = True
        self._set_state(self._rest_state(), now, "Home complete")
        return Ending(End.DONE, "Home complete")

    def _tilt_calibrated(self, ctl: TiltCalibrate, now: float) -> Ending | None:
        assert ctl.result is not None  # it finished DONE
        self.refs.tilt = True
        tilt = dataclasses.replace(ctl.result, at=now + self.wall_offset)
        return self._calibrated(Calibration(tilt=tilt, rotate=self.calibration.rotate), now)

    def _rotate_calibrated(self, ctl: RotateCalibrate, now: float) -> Ending | None:
        assert ctl.result is not None  # it finished DONE
        self.refs.tilt = self.refs.rotate = True
        rotate = dataclasses.replace(ctl.result, at=now + self.wall_offset)
        return self._calibrated(Calibration(tilt=self.calibration.tilt, rotate=rotate), now)

    def enter_calibration(self, values: CalibrationSet, now: float) -> SaveTicket | None:
        """A technician's values, recorded as manual: validated against the same plausible
        ranges a measurement must meet, refused while a motion is under way, then used at
        once and persisted (the ticket says when the write is done, and how)."""
        if self.is_moving() or self.action is not None or self._saving is not None:
            raise WrongState(
                f"calibration values cannot be entered in state {self.state} while a motion"
                " is under way (or its calibration is being saved); Stop it first"
            )
        cal = manual_calibration(values, self.config, self.calibration, now + self.wall_offset)
        # Not trusted until a Home has checked it with a measured move (docs/homing.md).
        self.refs.tilt &= values.tilt is None
        self.refs.rotate &= values.rotate is None
        ticket = self._use(cal)
        if self.state in REST_STATES and self.state is not S.DONE:
            self._set_state(self._rest_state(), now, "calibration entered by hand")
        return ticket

    def _use(self, cal: Calibration) -> SaveTicket | None:
        """Use `cal` from now on and persist it (the ticket of the write, if any)."""
        self.calibration = cal
        self.devices.tilt.calibration = cal.tilt
        ticket = self.on_calibrated(cal) if self.on_calibrated is not None else None
        self.save_ticket = ticket
        return ticket

    def _calibrated(self, cal: Calibration, now: float) -> Ending | None:
        """Use `cal` now and persist it; it has ended once the write has (None until then)."""
        ticket = self._use(cal)
        if ticket is None:
            self._set_state(self._rest_state(), now, "calibration complete")
            return Ending(End.DONE, "calibration complete")
        # Still CALIBRATING (outputs off, no controller) until the disk answers: a Rider that
        # waits for the calibration learns whether it was saved from the notice that ends it.
        self._saving = _Saving(ticket, self.action)
        if ticket.done:
            return self._saved(ticket, now)
        return None

    def _saved(self, ticket: SaveTicket, now: float) -> Ending:
        self._saving = None
        problem = ticket.problem
        why = "calibration complete" + (", NOT saved" if problem else "")
        if problem:
            ending = Ending(End.STORAGE_FAILED, problem, ErrorCode.STORAGE_FAILED.value)
        else:
            ending = Ending(End.DONE, "calibration complete")
        if self.state is S.CALIBRATING and self._drive.controller is None:
            self._set_state(self._rest_state(), now, why)
        return ending

    def _save_done(self, saving: _Saving, now: float) -> None:
        """A background save finished: the calibration waiting for it (if any) has ended."""
        ending = self._saved(saving.ticket, now)
        if self.action is not None and self.action is saving.motion:
            self._end(ending, now)

    def duplicate_id(self, others: tuple[str, ...], own: str, now: float) -> None:
        """Other sessions hold this machine's id (`others`, empty: alone again). Met: motion
        stops in this cycle (FAULT_HW, DUPLICATE_ID); alone again: the fault stays (it
        latches like any fault) and commands are taken again; nothing moves by itself."""
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
        self._enter_fault(fault, now, fault.code.value)

    def motion(self) -> Controller | None:
        """The controller that owns an axis now (running, paused or held by an E-stop)."""
        ctl = self._drive.controller
        return ctl.active() if ctl is not None else None

    def is_moving(self) -> bool:
        """Motion is under way or can be resumed (paused, or halted by a released E-stop)."""
        return self.state in MOTION_STATES or self._drive.controller is not None

    # ------------------------------------------------------------------- the Rider deadman
    def rider_lost(self, now: float) -> bool:
        """The controlling Rider is gone: apply the rider-loss policy now, or after the
        configured grace period if it does not come back; True if it acted now."""
        if self._rider.gone(now, self.config.rider_loss.grace_s):
            return self._apply_rider_loss(now)
        return False

    def rider_heartbeat(self, at: float | None, now: float) -> bool:
        """Deadman check, once per cycle: `at` is when the controlling Rider's heartbeat last
        arrived (None: never). Silent for `rider_loss.timeout_s` → lost; a heartbeat after a
        loss → back (a paused ride stays paused). True if the Rider was judged lost now."""
        if self._rider.id is None:
            return False
        if self._rider.silent(at, now, self.config.rider_loss.timeout_s):
            self.rider_lost(now)
            return True
        return False

    def rider_back(self) -> None:
        """The controlling Rider's token is back (within the grace period nothing happened)."""
        self._rider.back()

    def _apply_rider_loss(self, now: float) -> bool:
        self._rider.gone_at = None
        policy = self.config.rider_loss.policy
        if self.state not in MOTION_STATES or policy is RiderLossPolicy.IGNORE:
            return False
        self._rider.warning = f"controlling Rider lost during {self.state}; policy {policy}"
        if policy is RiderLossPolicy.PAUSE:
            self._pause(now, "Rider lost")
        else:
            self._stop(now, "Rider lost", "RIDER_LOST")
        return True

    def _set_state(self, new: MachineState, now: float, why: str) -> None:
        if new is self.state:
            return
        old = self.state
        self.previous_state, self.state = old, new
        if self.on_transition is not None:
            self.on_transition(Transition(old=old, new=new, reason=why, at=now + self.wall_offset))

    # ---------------------------------------------------------------------------- status
    def session_progress(self) -> SessionProgress | None:
        run = self._drive.session_run
        return run.progress() if run is not None else None

    def estop_info(self) -> EstopInfo:
        return EstopInfo(active=self.devices.safety.is_estop_active(), latched=self.estop_latched)

    def rest_key(self) -> tuple[object, ...] | None:
        """None while anything is pending that `update` acts on by itself as time passes (a
        controller, a calibration being saved, a lost Rider's grace period) or that the loop
        still has to take (a completion notice). Otherwise a fingerprint of everything
        `update`, the status and the event history read of this object: while it, the
        inputs and the clock's timers stay as they were, a cycle would change nothing
        (`ScanLoop`'s quiet cycles). Plain attribute reads: it is taken every idle cycle."""
        drive, rider = self._drive, self._rider
        if (
            drive.controller is not None
            or self._saving is not None
            or rider.gone_at is not None
            or self.completions
        ):
            return None
        storage = self.storage
        return (
            self.live.current,
            self.state,
            self.previous_state,
            self.fault,
            self.calibration,
            self.devices.tilt.calibration,
            self.refs.tilt,
            self.refs.rotate,
            drive.session_run,
            drive.resume_to,
            drive.estop_from,
            drive.estop_latched,
            self.action,
            rider,
            rider.id,
            rider.connected,
            rider.warning,
            self.duplicate_of,
            len(self.warnings),
            storage.version if storage is not None else 0,
        )

    def status_key(self) -> tuple[object, ...]:
        """Cheap fingerprint of everything in `Status` except positions and time."""
        run = self._drive.session_run
        refs, devices = self.refs, self.devices  # as `homed()`, without a model every cycle
        return (
            self.state,
            self.previous_state,
            self.fault,
            devices.safety.is_estop_active(),
            self.estop_latched,
            self.calibration,
            refs.tilt and devices.tilt.is_home(),
            refs.rotate and devices.rotate.is_home(),
            run.index if run is not None else None,
            run.revolutions_done() if run is not None else None,
            len(self.warnings),
            self.rider_warning,
            self.rider_connected,
            self.storage.version if self.storage is not None else 0,
            self.action.transaction_id if self.action is not None else None,
        )


# --------------------------------------------------------------------------------- table
_ANY = frozenset(S)
_REST = (S.IDLE, S.WARNING_NOT_HOME, S.WARNING_NEEDS_CALIBRATION)
"""The rest state, in the order it is chosen: IDLE when calibrated and home, else the warning."""
_A, _C, _R, _E = ControlAPI, Command, ReplyCode, Event

HANDLING: dict[Command, Handling] = {
    _C.CALIBRATE_TILT: Handling(_A._calibrate_tilt, _R.RESP_CALIBRATION_ACCEPTED, moves=True),
    _C.CALIBRATE_ROTATE: Handling(_A._calibrate_rotate, _R.RESP_CALIBRATION_ACCEPTED, moves=True),
    _C.HOME: Handling(_A._home, _R.RESP_HOME_ACCEPTED, moves=True),
    _C.START: Handling(_A._start, _R.RESP_START_ACCEPTED, moves=True),
    _C.PAUSE: Handling(_A._pause_command, _R.RESP_PAUSED),
    _C.RESUME: Handling(_A._resume_command, _R.RESP_RESUMED, moves=True),
    _C.STOP: Handling(_A._stop_command, _R.RESP_DONE),
    _C.CHECK_CALIBRATION: Handling(_A._check_calibration, _R.RESP_CHECK, read_only=True),
    _C.CHECK_HOME: Handling(_A._check_home, _R.RESP_CHECK, read_only=True),
}
"""One handler per command, with the reply it earns."""

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
    ),
    Rule(_C.PAUSE, ALLOWED_STATES[_C.PAUSE], (S.PAUSED,), "controller halted, relays off"),
    Rule(
        _C.RESUME,
        frozenset({S.PAUSED}),
        (S.HOMING, S.CALIBRATING, S.RUNNING, *_REST),
        "back to the state before Pause (the rest state if nothing is left to run)",
    ),
    Rule(
        _C.RESUME,
        frozenset({S.FAULT_ESTOP}),
        tuple(s for s in S if s is not S.FAULT_ESTOP),
        "back to the state before the E-stop (a motion goes on)",
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
    ),
    Rule(
        _E.ESTOP,
        _ANY - {S.FAULT_ESTOP},
        (S.FAULT_ESTOP,),
        "relays dropped in the same cycle, controller halted, latched",
    ),
    Rule(_E.MOTION_DONE, frozenset({S.HOMING}), _REST, "both axes referenced; the rest state"),
    Rule(
        _E.MOTION_DONE,
        frozenset({S.CALIBRATING}),
        _REST,
        "calibration in use; the rest state once it is saved",
    ),
    Rule(_E.MOTION_DONE, frozenset({S.RUNNING}), (S.DONE,), "session complete"),
    Rule(
        _E.SAVED,
        frozenset({S.CALIBRATING}),
        _REST,
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
    ),
    Rule(
        _E.CALIBRATION_ENTERED,
        REST_STATES - {S.DONE},
        _REST,
        "a technician's values: the rest state (that axis not home until Home checks them)",
    ),
)
"""The machine's behaviour, row by row: the command guard and the docs read it; the tests
check that what the machine does stays inside it."""

_ACCEPTED: dict[Command, frozenset[MachineState]] = {
    command: frozenset().union(*(r.sources for r in TABLE if r.trigger is command))
    for command in Command
}
_ACCEPTED_TEXT = {command: ", ".join(sorted(states)) for command, states in _ACCEPTED.items()}
"""The states a WRONG_STATE refusal names, sorted once (a refusal per command under a storm)."""


def edges() -> frozenset[tuple[MachineState, MachineState]]:
    """Every (old, new) state change the table allows."""
    return frozenset((s, t) for r in TABLE for s in r.sources for t in r.targets if s is not t)
