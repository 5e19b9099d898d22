"""The machine's handlers: a command's admission and guard, then its one action, then its reply.

An action does what its command does (begin a motion, pause, answer a check) and changes the
state through the table (`StateMachine.go`/`enter`); a refusal raises a `MachineError`, which
`handle` turns into the reply.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from schema.commands import (
    DEFAULT_SESSION,
    REST_STATES,
    CheckResult,
    Command,
    CommandRequest,
    Reply,
    RotateStep,
    Session,
    StartRequest,
    TiltStep,
)
from schema.completion import Outcome
from schema.status import Fault, FaultCode, MachineState
from service.core.admission import admit
from service.core.calibrate import RotateCalibrate, TiltCalibrate, TiltVerify
from service.core.controllers import SessionRun
from service.core.homing import RotateHome, TiltHome
from service.core.motion import Chain, Controller
from service.core.statemachine import calibration
from service.core.statemachine.context import Ending, Motion, Plan, never
from service.core.statemachine.deadman import RiderWatch
from service.core.statemachine.table import ACCEPTED_TEXT, HANDLING, Event, allowed_states
from service.errors import (
    DuplicateId,
    EstopActive,
    InvalidSession,
    MachineError,
    NotCalibrated,
    NotHome,
    WrongState,
)

if TYPE_CHECKING:
    from service.core.statemachine.machine import StateMachine

S = MachineState
C = Command

Handler = Callable[["StateMachine", CommandRequest, float], "CheckResult | None"]
"""A command's action: it changes the state (or raises a `MachineError`) and may return a
check result for the reply."""


def handle(m: StateMachine, command: Command, request: CommandRequest, now: float) -> Reply:
    """Act on one command and say what happened; refusals change nothing but the reply."""
    stamp = now + m.wall_offset
    handling = HANDLING[command]
    try:
        if handling.moves:
            admit(command, request, stamp, m.config.bus.clock_margin_s)
        if not handling.read_only:
            _guard(m, command)
        result = ACTIONS[command](m, request, now)
    except MachineError as exc:
        return Reply.failure(
            exc.to_error(),
            transaction_id=request.transaction_id,
            command=command.value,
            timecode=stamp,
            state=m.state,
            request_timecode=request.timecode,
        )
    if handling.moves:  # the command itself is a sign of life
        m.watch = RiderWatch(request.rider, request.rider is not None, heard_at=now)
    return Reply(
        transaction_id=request.transaction_id,
        command=command._value_,
        timecode=stamp,
        request_timecode=request.timecode,
        success=True,
        code=handling.reply,
        state=m.state,
        result=result,
    )


def _guard(m: StateMachine, command: Command) -> None:
    """Refuse a command this machine cannot take now: id held twice, E-stop, state."""
    if m.duplicate_of:
        raise DuplicateId(
            f"{command.value} refused: machine id {m.config.machine.id} is also held by"
            f" session {', '.join(m.duplicate_of)}; nothing is taken until one of the"
            " two daemons is stopped or given another id"
        )
    if m.devices.safety.is_estop_active():
        raise EstopActive(
            f"{command.value} refused: the E-stop is active; release it, then Resume, Home or Stop"
        )
    if m.state not in allowed_states(command):
        raise WrongState(
            f"{command.value} is not accepted in state {m.state};"
            f" accepted in: {ACCEPTED_TEXT[command]}"
        )


def calibrate_tilt(m: StateMachine, request: CommandRequest, now: float) -> None:
    tilt = TiltCalibrate(m.devices.tilt, m.config.tilt)
    plan = Plan(C.CALIBRATE_TILT, m.target(C.CALIBRATE_TILT), tilt, _tilt_done(m, tilt))
    m.begin(request, plan, now)


def calibrate_rotate(m: StateMachine, request: CommandRequest, now: float) -> None:
    rotate = RotateCalibrate(m.devices.rotate, m.config.rotate)
    chain = Chain([lambda: tilt_home(m), lambda: rotate])
    target = m.target(C.CALIBRATE_ROTATE)
    m.begin(request, Plan(C.CALIBRATE_ROTATE, target, chain, _rotate_done(m, rotate)), now)


def _tilt_done(m: StateMachine, ctl: TiltCalibrate) -> Callable[[float], Ending | None]:
    return lambda now: calibration.tilt_measured(m, ctl, now)


def _rotate_done(m: StateMachine, ctl: RotateCalibrate) -> Callable[[float], Ending | None]:
    return lambda now: calibration.rotate_measured(m, ctl, now)


def home(m: StateMachine, request: CommandRequest, now: float) -> None:
    chain = Chain([lambda: tilt_home(m), lambda: rotate_home(m)])

    def homed(at: float) -> Ending:
        m.refs.tilt = m.refs.rotate = True
        m.go(Event.MOTION_DONE, at, "Home complete")
        return Ending(Outcome.DONE, "Home complete")

    m.begin(request, Plan(C.HOME, m.target(C.HOME), chain, homed), now)


def tilt_home(m: StateMachine) -> Controller:
    """The tilt's part of Home (and of CalibrateRotate): an entered calibration not verified
    yet is verified on the way (`TiltVerify`), a trusted one checked at its zero."""
    tilt, cfg = m.devices.tilt, m.config.tilt
    if tilt.calibration is not None and not tilt.calibration.verified:
        return TiltVerify(tilt, cfg)
    return TiltHome(tilt, cfg)


def rotate_home(m: StateMachine) -> Controller:
    cal = m.calibration.rotate
    speed = cal.speed_dps if cal is not None else None
    return RotateHome(m.devices.rotate, m.config.rotate, speed)


def start(m: StateMachine, request: CommandRequest, now: float) -> None:
    """The seed's Session(): CheckCalibrate, CheckHome, CheckSession, then run. A check that
    fails sets its state (the table's Start row picks it), then ends this Start with a notice
    (the seed's "send WARNING…, stop session, send DONE"), and the reply says why."""
    session = request.session if isinstance(request, StartRequest) else None
    session = session or DEFAULT_SESSION
    target = m.target(C.START, session)
    if target is S.RUNNING:
        assert m.calibration.rotate is not None  # the checks passed: calibrated
        run = SessionRun(session, m.devices, m.config, m.calibration.rotate)
        why = f"Start session {session.name!r}"
        m.begin(request, Plan(C.START, target, run, session_done(m), why, run), now)
        return
    outcome, error = _refused(m, target, session, now)
    motion = Motion(C.START, request.transaction_id, request.rider, now + m.wall_offset, never)
    m.notify(motion, Ending(outcome, error.message, error.code.value), now)
    raise error


def start_target(m: StateMachine, session: Session | None) -> MachineState:
    """`Pick.START_CHECKS`: the state of the first of Start's checks that fails, else RUNNING."""
    if not m.calibration.complete:
        return S.WARNING_NEEDS_CALIBRATION
    home = m.homed()
    if not (home.tilt and home.rotate):
        return S.WARNING_NOT_HOME
    if session is not None and session_problem(m, session) is not None:
        return S.FAULT_HW
    return S.RUNNING


def _refused(
    m: StateMachine, target: MachineState, session: Session, now: float
) -> tuple[Outcome, MachineError]:
    """Enter the state of the check that failed; how the Start ends, and its refusal."""
    if target is S.WARNING_NEEDS_CALIBRATION:
        missing = [a for a in ("tilt", "rotate") if getattr(m.calibration, a) is None]
        m.enter(C.START, target, now, "Start: not calibrated")
        return Outcome.REFUSED, NotCalibrated(
            f"Start refused: {' and '.join(missing)} not calibrated"
        )
    if target is S.WARNING_NOT_HOME:
        home = m.homed()
        missing = [a for a in ("tilt", "rotate") if not getattr(home, a)]
        m.enter(C.START, target, now, "Start: not home")
        return Outcome.REFUSED, NotHome(
            f"Start refused: {' and '.join(missing)} not home; send Home first"
        )
    problem = session_problem(m, session)
    assert problem is not None  # the pick chose FAULT_HW for it
    path, message = problem
    fault = Fault(code=FaultCode.INVALID_SESSION, message=message)
    m.enter_fault(fault, now, "Start: bad session", C.START, moved=False)
    return Outcome.FAULT_HW, InvalidSession(message, path)


def session_problem(m: StateMachine, session: Session) -> tuple[str, str] | None:
    """The first step this machine cannot do, as (JSON pointer, message)."""
    lo, hi = m.config.tilt.min_deg, m.config.tilt.max_deg
    for i, step in enumerate(session.steps):
        if isinstance(step, TiltStep) and not lo <= step.degrees <= hi:
            return (
                f"/session/steps/{i}/degrees",
                f"step {i}: tilt {step.degrees:g}° is outside this machine's range {lo:g}..{hi:g}°",
            )
        if isinstance(step, RotateStep) and step.revolutions < 1:
            return (f"/session/steps/{i}/revolutions", f"step {i}: revolutions must be ≥ 1")
    return None


def session_done(m: StateMachine) -> Callable[[float], Ending]:
    def done(now: float) -> Ending:
        m.go(Event.MOTION_DONE, now, "session complete")
        return Ending(Outcome.DONE, "session complete")

    return done


def pause(m: StateMachine, request: CommandRequest, now: float) -> None:
    m.pause(now, "Pause")


def resume(m: StateMachine, request: CommandRequest, now: float) -> None:
    m.resume(now)


def stop(m: StateMachine, request: CommandRequest, now: float) -> None:
    m.stop(now, "Stop")


def check_calibration(m: StateMachine, request: CommandRequest, now: float) -> CheckResult:
    cal = m.calibration
    result = CheckResult(ok=cal.complete, tilt=cal.tilt is not None, rotate=cal.rotate is not None)
    state = m.state
    if state in REST_STATES:
        if not result.ok and state is not S.WARNING_NEEDS_CALIBRATION:
            m.go(C.CHECK_CALIBRATION, now, "CheckCalibration failed")
        elif result.ok and state is S.WARNING_NEEDS_CALIBRATION:
            m.go(C.CHECK_CALIBRATION, now, "CheckCalibration passed")
    return result


def check_home(m: StateMachine, request: CommandRequest, now: float) -> CheckResult:
    home = m.homed()
    result = CheckResult(ok=home.tilt and home.rotate, tilt=home.tilt, rotate=home.rotate)
    # Needing calibration is the bigger problem: that warning is not hidden (no row moves it).
    state = m.state
    if not result.ok and state in (S.IDLE, S.DONE):
        m.go(C.CHECK_HOME, now, "CheckHome failed")
    elif result.ok and state is S.WARNING_NOT_HOME:
        m.go(C.CHECK_HOME, now, "CheckHome passed")
    return result


ACTIONS: dict[Command, Handler] = {
    C.CALIBRATE_TILT: calibrate_tilt,
    C.CALIBRATE_ROTATE: calibrate_rotate,
    C.HOME: home,
    C.START: start,
    C.PAUSE: pause,
    C.RESUME: resume,
    C.STOP: stop,
    C.CHECK_CALIBRATION: check_calibration,
    C.CHECK_HOME: check_home,
}
"""One action per command (its reply and kind: `table.HANDLING`)."""
