"""`ControlAPI`: the machine's state machine. Pure logic: no IO, no clock, time comes in."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from schema.calibration import CalibrationSet, CalibrationSource
from schema.commands import (
    ALLOWED_STATES,
    DEFAULT_SESSION,
    READ_ONLY_COMMANDS,
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
from service.config import LiveConfig, MachineConfig, RiderLossPolicy
from service.controllers import (
    Chain,
    Controller,
    Outcome,
    RotateCalibrate,
    RotateHome,
    SessionRun,
    TiltCalibrate,
    TiltHome,
)
from service.devices import Calibration, Devices, RotateCalibration, TiltCalibration
from service.errors import (
    BadRequest,
    DuplicateId,
    EstopActive,
    InvalidSession,
    MachineError,
    NotCalibrated,
    NotHome,
    ParamOutOfRange,
    WrongState,
)

if TYPE_CHECKING:  # types only: the state machine does no IO
    from service.persist import SaveTicket, StorageHealth

S = MachineState
_ALLOWED = ALLOWED_STATES
READ_ONLY = READ_ONLY_COMMANDS
_CALIBRATIONS = frozenset({Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE})
MOVING_COMMANDS = frozenset(
    {Command.START, Command.HOME, Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE, Command.RESUME}
)
"""Commands that set the machine moving: their sender becomes the controlling Rider."""


def _never(ctl: Controller, now: float) -> Ending | None:
    """The `on_done` of a notice that ends a command before any motion began."""
    raise AssertionError("no controller runs for a refused Start")


def allowed_states(command: Command) -> frozenset[MachineState]:
    """The states in which `command` is accepted (E-stop released)."""
    return _ALLOWED[command]


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


OnDone = Callable[["Controller", float], "Ending | None"]
"""What to do when a motion's controller finishes: settle the state and say how it ended
(None: not ended yet, e.g. a calibration whose save is still under way)."""


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
        self.state = (
            S.WARNING_NEEDS_CALIBRATION if not self.calibration.complete else S.WARNING_NOT_HOME
        )
        self.previous_state: MachineState | None = None
        self.fault: Fault | None = None
        self.controller: Controller | None = None
        self.session_run: SessionRun | None = None
        self.estop_latched = False
        self.rider_connected = False
        self.controller_rider: str | None = None
        self._rider_gone_at: float | None = None
        self._rider_heard_at = 0.0
        self.duplicate_of: tuple[str, ...] = ()
        """Other sessions holding this machine's id (the bus watches `holder/<zid>`)."""
        self.rider_warning: str | None = None
        self._resume_to: MachineState | None = None
        self._estop_from: MachineState | None = None
        self.action: Motion | None = None
        """The motion command whose completion notice is still due (running, paused,
        E-stopped), like a ROS 2 action goal; `motion()` is the controller driving it."""
        self.completions: list[Completion] = []
        """Notices produced and not yet taken by the scan loop (`take_completions`)."""
        self._saving: SaveTicket | None = None
        self.devices.stop_all()

    # ------------------------------------------------------------------------- commands
    def handle(self, command: Command, request: CommandRequest, now: float) -> Reply:
        """Act on one command and say what happened; refusals change nothing but the reply."""
        stamp = now + self.wall_offset
        try:
            code, result = self._dispatch(command, request, now)
            if command in MOVING_COMMANDS:
                self.controller_rider = request.rider
                self.rider_connected = request.rider is not None
                self._rider_gone_at = None
                self._rider_heard_at = now  # the command itself is a sign of life
        except MachineError as exc:
            return Reply.failure(
                exc.to_error(),
                transaction_id=request.transaction_id,
                command=command.value,
                timecode=stamp,
                state=self.state,
                request_timecode=request.timecode,
            )
        return Reply(
            transaction_id=request.transaction_id,
            command=command.value,
            timecode=stamp,
            request_timecode=request.timecode,
            success=True,
            code=code,
            state=self.state,
            result=result,
        )

    def _dispatch(
        self, command: Command, request: CommandRequest, now: float
    ) -> tuple[ReplyCode, CheckResult | None]:
        if command is Command.CHECK_CALIBRATION:
            return ReplyCode.RESP_CHECK, self._check_calibration(now)
        if command is Command.CHECK_HOME:
            return ReplyCode.RESP_CHECK, self._check_home(now)
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
        if self.state not in _ALLOWED[command]:
            allowed = ", ".join(sorted(_ALLOWED[command]))
            raise WrongState(
                f"{command.value} is not accepted in state {self.state}; accepted in: {allowed}"
            )
        if command is Command.START:
            session = request.session if isinstance(request, StartRequest) else None
            self._start(session or DEFAULT_SESSION, request, now)
            return ReplyCode.RESP_START_ACCEPTED, None
        if command is Command.HOME:
            home = Chain([self._tilt_home, self._rotate_home])
            self.begin(request, Command.HOME, S.HOMING, home, now, on_done=self._homed)
            return ReplyCode.RESP_HOME_ACCEPTED, None
        if command is Command.CALIBRATE_TILT:
            tilt = TiltCalibrate(self.devices.tilt, self.config.tilt)
            self.begin(request, command, S.CALIBRATING, tilt, now, on_done=self._tilt_calibrated)
            return ReplyCode.RESP_CALIBRATION_ACCEPTED, None
        if command is Command.CALIBRATE_ROTATE:
            rotate = self.devices.rotate

            def calibrate() -> Controller:
                return RotateCalibrate(rotate, self.config.rotate)

            chain = Chain([self._tilt_home, calibrate])
            self.begin(request, command, S.CALIBRATING, chain, now, on_done=self._rotate_calibrated)
            return ReplyCode.RESP_CALIBRATION_ACCEPTED, None
        if command is Command.PAUSE:
            self._pause(now, "Pause")
            return ReplyCode.RESP_PAUSED, None
        if command is Command.RESUME:
            self._resume(now)
            return ReplyCode.RESP_RESUMED, None
        self._stop(now, "Stop")
        return ReplyCode.RESP_DONE, None

    def _tilt_home(self) -> Controller:
        return TiltHome(self.devices.tilt, self.config.tilt)

    def _rotate_home(self) -> Controller:
        return RotateHome(self.devices.rotate, self.config.rotate)

    def _start(self, session: Session, request: CommandRequest, now: float) -> None:
        """The seed's Session(): CheckCalibrate, CheckHome, CheckSession, then run. A check
        that fails sets its state, then ends this Start with a notice (the seed's "send
        WARNING…, stop session, send DONE"), and the reply says why."""
        if not self.calibration.complete:
            missing = [a for a in ("tilt", "rotate") if getattr(self.calibration, a) is None]
            self._set_state(S.WARNING_NEEDS_CALIBRATION, now, "Start: not calibrated")
            error: MachineError = NotCalibrated(
                f"Start refused: {' and '.join(missing)} not calibrated"
            )
            self._notice_refused(request, End.REFUSED, error, now)
            raise error
        home = self.homed()
        if not (home.tilt and home.rotate):
            missing = [a for a in ("tilt", "rotate") if not getattr(home, a)]
            self._set_state(S.WARNING_NOT_HOME, now, "Start: not home")
            error = NotHome(f"Start refused: {' and '.join(missing)} not home; send Home first")
            self._notice_refused(request, End.REFUSED, error, now)
            raise error
        problem = self._session_problem(session)
        if problem is not None:
            path, message = problem
            self._enter_fault(
                Fault(code=FaultCode.INVALID_SESSION, message=message), now, "Start: bad session"
            )
            error = InvalidSession(message, path)
            self._notice_refused(request, End.FAULT_HW, error, now)
            raise error
        assert self.calibration.rotate is not None  # checked complete above
        run = SessionRun(
            session,
            self.devices.tilt,
            self.devices.rotate,
            self.config.tilt,
            self.config.rotate,
            self.calibration.rotate.home_arc_deg,
        )
        self.session_run = run
        why = f"Start session {session.name!r}"
        self.begin(request, Command.START, S.RUNNING, run, now, on_done=self._session_done, why=why)

    def _notice_refused(
        self, request: CommandRequest, outcome: End, error: MachineError, now: float
    ) -> None:
        wall = now + self.wall_offset
        motion = Motion(Command.START, request.transaction_id, request.rider, wall, _never)
        self._notify(motion, Ending(outcome, error.message, error.code.value), now)

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

    def begin(
        self,
        request: CommandRequest,
        command: Command,
        state: MachineState,
        ctl: Controller,
        now: float,
        *,
        on_done: OnDone,
        why: str | None = None,
    ) -> None:
        """Start a motion: `ctl` runs in `state`; when it finishes, `on_done` settles the
        state and says how it ended, and that becomes the motion's one completion notice."""
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
        self._discard_controller()
        if command is not Command.START:
            self.session_run = None
        self.controller = ctl
        self.action = Motion(
            command, request.transaction_id, request.rider, now + self.wall_offset, on_done
        )
        self.fault = None
        self.rider_warning = None
        self.estop_latched = False
        self._resume_to = self._estop_from = None
        self._set_state(state, now, why or command.value)

    def _pause(self, now: float, why: str) -> None:
        if self.controller is not None:
            self.controller.halt()
        self._resume_to = self.state
        self._set_state(S.PAUSED, now, why)

    def _resume(self, now: float) -> None:
        self.rider_warning = None  # whoever resumes has taken over
        if self.state is S.FAULT_ESTOP:
            target = self._estop_from or self._rest_state()
            self.estop_latched = False
            self._estop_from = None
            if target is S.PAUSED:
                self._set_state(S.PAUSED, now, "Resume after E-stop (still paused)")
                return
        else:
            target = self._resume_to or self._rest_state()
            self._resume_to = None
        if target in MOTION_STATES and self.controller is not None:
            self.controller.resume(now)
        elif target in MOTION_STATES:
            target = self._rest_state()
        self._set_state(target, now, "Resume")

    def _stop(self, now: float, why: str, code: str | None = None) -> None:
        after_estop = self.state is S.FAULT_ESTOP
        self._discard_controller()
        self.session_run = None
        self.fault = None
        self.estop_latched = False
        self._resume_to = self._estop_from = None
        self._set_state(S.DONE, now, why)
        self._end(Ending(End.STOPPED, why + (" after an E-stop" if after_estop else ""), code), now)

    def _discard_controller(self) -> None:
        if self.controller is not None:
            self.controller.abandon()
        self.controller = None
        self.devices.stop_all()

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

    # ---------------------------------------------------------------------------- checks
    def _check_calibration(self, now: float) -> CheckResult:
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

    def _check_home(self, now: float) -> CheckResult:
        home = self.homed()
        result = CheckResult(ok=home.tilt and home.rotate, tilt=home.tilt, rotate=home.rotate)
        if self.state in REST_STATES:
            # Needing calibration is the bigger problem: that warning is not hidden.
            if not result.ok and self.state is not S.WARNING_NEEDS_CALIBRATION:
                self._set_state(S.WARNING_NOT_HOME, now, "CheckHome failed")
            elif self.state is S.WARNING_NOT_HOME:
                self._set_state(self._rest_state(), now, "CheckHome passed")
        return result

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
        if self.controller is not None:
            self.controller.halt()
        self.devices.stop_all()
        if self.state is not S.FAULT_ESTOP:
            self._estop_from = self.state
            self.estop_latched = True
            self._set_state(S.FAULT_ESTOP, now, "E-stop pressed")

    def update(self, now: float) -> None:
        """Step the active controller; in every other state hold all outputs off."""
        gone = self._rider_gone_at
        if gone is not None and now - gone >= self.config.rider_loss.grace_s:
            self._apply_rider_loss(now)
        if self._saving is not None and self._saving.done:
            self._save_done(self._saving, now)
        ctl = self.controller
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
        self._finish(ctl, now)

    def _finish(self, ctl: Controller, now: float) -> None:
        motion = self.action
        self.controller = None
        self.devices.stop_all()
        assert motion is not None, "a controller runs only as part of a motion"
        ending = motion.on_done(ctl, now)
        if ending is not None:
            self._end(ending, now)

    # The `on_done` actions, bound when each motion begins.
    def _session_done(self, ctl: Controller, now: float) -> Ending:
        self._set_state(S.DONE, now, "session complete")
        return Ending(End.DONE, "session complete")

    def _homed(self, ctl: Controller, now: float) -> Ending:
        self.refs.tilt = self.refs.rotate = True
        self._set_state(self._rest_state(), now, "Home complete")
        return Ending(End.DONE, "Home complete")

    def _tilt_calibrated(self, ctl: Controller, now: float) -> Ending | None:
        assert isinstance(ctl, TiltCalibrate) and ctl.result is not None
        self.refs.tilt = True
        tilt = dataclasses.replace(ctl.result, at=now + self.wall_offset)
        return self._calibrated(Calibration(tilt=tilt, rotate=self.calibration.rotate), now)

    def _rotate_calibrated(self, ctl: Controller, now: float) -> Ending | None:
        assert isinstance(ctl, Chain)
        cal = ctl.finished[-1]
        assert isinstance(cal, RotateCalibrate) and cal.result is not None
        self.refs.tilt = self.refs.rotate = True
        rotate = dataclasses.replace(cal.result, at=now + self.wall_offset)
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
        if values.tilt is None and values.rotate is None:
            raise BadRequest("give tilt values, rotate values or both", "/tilt")
        wall = now + self.wall_offset
        manual = CalibrationSource.MANUAL
        tilt, rotate = self.calibration.tilt, self.calibration.rotate
        if values.tilt is not None:
            t = values.tilt
            lo, hi = (
                self.config.tilt.gain_min_counts_per_deg,
                self.config.tilt.gain_max_counts_per_deg,
            )
            if not lo <= t.gain_counts_per_deg <= hi:
                raise ParamOutOfRange(
                    f"tilt gain {t.gain_counts_per_deg:g} counts/° is outside this machine's"
                    f" plausible {lo:g}..{hi:g} (tilt.gain_min/max_counts_per_deg)",
                    "/tilt/gain_counts_per_deg",
                )
            tilt = TiltCalibration(t.offset_counts, t.gain_counts_per_deg, manual, wall)
        if values.rotate is not None:
            r = values.rotate
            nominal = 360.0 / self.config.rotate.nominal_speed_dps
            tol = self.config.rotate.speed_tolerance
            if not nominal * (1 - tol) <= r.revolution_s <= nominal * (1 + tol):
                raise ParamOutOfRange(
                    f"revolution time {r.revolution_s:g} s is outside {nominal:.3f} s ± {tol:.0%}"
                    " (rotate.nominal_speed_dps, rotate.speed_tolerance)",
                    "/rotate/revolution_s",
                )
            rotate = RotateCalibration(r.revolution_s, r.home_arc_deg, manual, wall)
        cal = Calibration(tilt=tilt, rotate=rotate)
        self.calibration = cal
        self.devices.tilt.calibration = cal.tilt
        if self.state in REST_STATES and self.state is not S.DONE:
            self._set_state(self._rest_state(), now, "calibration entered by hand")
        return self.on_calibrated(cal) if self.on_calibrated is not None else None

    def _calibrated(self, cal: Calibration, now: float) -> Ending | None:
        """Use `cal` now and persist it; it has ended once the write has (None until then)."""
        self.calibration = cal
        self.devices.tilt.calibration = cal.tilt
        ticket = self.on_calibrated(cal) if self.on_calibrated is not None else None
        if ticket is None:
            self._set_state(self._rest_state(), now, "calibration complete")
            return Ending(End.DONE, "calibration complete")
        # Still CALIBRATING (outputs off, no controller) until the disk answers: a Rider that
        # waits for the calibration learns whether it was saved from the notice that ends it.
        self._saving = ticket
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
        if self.state is S.CALIBRATING and self.controller is None:
            self._set_state(self._rest_state(), now, why)
        return ending

    def _save_done(self, ticket: SaveTicket, now: float) -> None:
        """A background save finished: the calibration waiting for it (if any) has ended."""
        ending = self._saved(ticket, now)
        motion = self.action
        if motion is not None and self.controller is None and motion.command in _CALIBRATIONS:
            self._end(ending, now)

    def _enter_fault(self, fault: Fault, now: float, why: str) -> None:
        self._discard_controller()
        self.session_run = None
        self.fault = fault
        self.refs.tilt = self.refs.rotate = False
        self._resume_to = self._estop_from = None
        self.estop_latched = False  # a still-pressed E-stop latches again next cycle
        self._set_state(S.FAULT_HW, now, f"{why}: {fault.message}")
        self._end(Ending(End.FAULT_HW, fault.message, fault.code.value), now)

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
        ctl = self.controller
        return ctl.active() if isinstance(ctl, Chain) else ctl

    def is_moving(self) -> bool:
        """Motion is under way or can be resumed (paused, or halted by a released E-stop)."""
        return self.state in MOTION_STATES or self.controller is not None

    def rider_lost(self, now: float) -> bool:
        """The controlling Rider is gone: apply the rider-loss policy now, or after the
        configured grace period if it does not come back; True if it acted now."""
        self.rider_connected = False
        if self.config.rider_loss.grace_s > 0:
            self._rider_gone_at = now
            return False
        return self._apply_rider_loss(now)

    def rider_heartbeat(self, at: float | None, now: float) -> bool:
        """Deadman check, once per cycle: `at` is when the controlling Rider's heartbeat last
        arrived (None: never). Silent for `rider_loss.timeout_s` → lost; a heartbeat after a
        loss → back. True if the Rider was judged lost now."""
        if self.controller_rider is None:
            return False
        if at is not None and at > self._rider_heard_at:
            self._rider_heard_at = at
            if not self.rider_connected:
                self.rider_back()  # nothing moves by itself: a paused ride stays paused
        if self.rider_connected and now - self._rider_heard_at > self.config.rider_loss.timeout_s:
            self.rider_lost(now)
            return True
        return False

    def rider_back(self) -> None:
        """The controlling Rider's token is back (within the grace period nothing happened)."""
        self.rider_connected = True
        self._rider_gone_at = None

    def _apply_rider_loss(self, now: float) -> bool:
        self._rider_gone_at = None
        policy = self.config.rider_loss.policy
        if self.state not in MOTION_STATES or policy is RiderLossPolicy.IGNORE:
            return False
        self.rider_warning = f"controlling Rider lost during {self.state}; policy {policy}"
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
        return self.session_run.progress() if self.session_run is not None else None

    def estop_info(self) -> EstopInfo:
        return EstopInfo(active=self.devices.safety.is_estop_active(), latched=self.estop_latched)

    def status_key(self) -> tuple[object, ...]:
        """Cheap fingerprint of everything in `Status` except positions and time."""
        run = self.session_run
        home = self.homed()
        return (
            self.state,
            self.previous_state,
            self.fault,
            self.devices.safety.is_estop_active(),
            self.estop_latched,
            self.calibration,
            home.tilt,
            home.rotate,
            run.index if run is not None else None,
            run.revolutions_done() if run is not None else None,
            len(self.warnings),
            self.rider_warning,
            self.rider_connected,
            self.storage.version if self.storage is not None else 0,
            self.action.transaction_id if self.action is not None else None,
        )
