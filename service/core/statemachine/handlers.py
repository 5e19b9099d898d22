"""The machine's handlers: what each command asks for, as one value the state machine carries
out (`Order`); a motion's `on_done`, bound here, fires the trigger that ends it.

A handler reads the machine's parts and builds: the motion to begin (`Plan`), a check's answer
(`Check`), a Start its checks refused (`Refusal`), or the command itself, whose transition the
machine makes (Pause, Resume, Stop). It never changes the state: `StateMachine.handle` calls
it once and does what it returns (the request stays with the machine).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from ride_machine.schema.commands import REST_STATES, CheckResult, Command
from ride_machine.schema.completion import Outcome
from ride_machine.schema.status import Fault, FaultCode, MachineState
from ride_machine.service.config.model import LiveConfig
from ride_machine.service.core.motion.base import Chain, Controller
from ride_machine.service.core.motion.calibrate import RotateCalibrate, TiltCalibrate, TiltVerify
from ride_machine.service.core.motion.controllers import SessionRun
from ride_machine.service.core.motion.devices import Devices
from ride_machine.service.core.motion.homing import RotateHome, TiltHome
from ride_machine.service.errors import InvalidSession, MachineError, NotCalibrated, NotHome

from .calibration import COMPLETE, CalibrationKeeper
from .context import Ending, MotionContext, OnDone, Plan
from .guards import Facts, start_checks
from .table import Occurrence, Trigger

S = MachineState
C = Command


class Machine(Protocol):
    """What a handler reads of the state machine, and the one call a motion's end makes."""

    devices: Devices
    live: LiveConfig
    keeper: CalibrationKeeper
    context: MotionContext
    wall_offset: float
    state: MachineState

    def go(self, trigger: Trigger, now: float, why: str) -> None: ...


@dataclass(frozen=True, slots=True)
class Check:
    """A check's answer, and the reason of the state change it makes (None: none)."""

    result: CheckResult
    why: str | None = None


@dataclass(frozen=True, slots=True)
class Refusal:
    """A Start one of its checks refused: the state the table picked for it is entered (for
    `fault`: FAULT_HW), the Start ends with a notice, and the reply is `error`."""

    why: str
    outcome: Outcome
    error: MachineError
    fault: Fault | None = None


Order = Plan | Check | Refusal | Command
"""What a handler asks of the machine (a `Command`: its own transition, Pause/Resume/Stop)."""

Handler = Callable[[Machine, Facts], Order]
"""A command's handler: the machine's parts, and what the table's guards read now (a Start's
session among them). The request is the machine's: who asked is its bookkeeping."""


def calibrate_tilt(m: Machine, facts: Facts) -> Plan:
    tilt = TiltCalibrate(m.devices.tilt, m.live.current.tilt)

    def measured(now: float) -> Ending | None:
        wall = now + m.wall_offset
        return _calibrated(m, m.keeper.tilt_measured(tilt, wall, m.context.action), now)

    return Plan(C.CALIBRATE_TILT, tilt, measured)


def calibrate_rotate(m: Machine, facts: Facts) -> Plan:
    rotate = RotateCalibrate(m.devices.rotate, m.live.current.rotate)

    def measured(now: float) -> Ending | None:
        wall = now + m.wall_offset
        return _calibrated(m, m.keeper.rotate_measured(rotate, wall, m.context.action), now)

    return Plan(C.CALIBRATE_ROTATE, Chain([lambda: tilt_home(m), lambda: rotate]), measured)


def _calibrated(m: Machine, done: bool, now: float) -> Ending | None:
    """A calibration in use: its motion is done now, or once its write ends (`SAVED`)."""
    if not done:
        return None
    m.go(Occurrence.MOTION_DONE, now, COMPLETE)
    return Ending(Outcome.DONE, COMPLETE)


def home(m: Machine, facts: Facts) -> Plan:
    chain = Chain([lambda: tilt_home(m), lambda: rotate_home(m)])

    def homed(at: float) -> Ending:
        m.keeper.homed_both()
        m.go(Occurrence.MOTION_DONE, at, "Home complete")
        return Ending(Outcome.DONE, "Home complete")

    return Plan(C.HOME, chain, homed)


def tilt_home(m: Machine) -> Controller:
    """The tilt's part of Home (and of CalibrateRotate): an entered calibration not verified
    yet is verified on the way (`TiltVerify`), a trusted one checked at its zero."""
    tilt, cfg = m.devices.tilt, m.live.current.tilt
    if tilt.calibration is not None and not tilt.calibration.verified:
        return TiltVerify(tilt, cfg)
    return TiltHome(tilt, cfg)


def rotate_home(m: Machine) -> Controller:
    cal = m.keeper.calibration.rotate
    speed = cal.speed_dps if cal is not None else None
    return RotateHome(m.devices.rotate, m.live.current.rotate, speed)


def start(m: Machine, facts: Facts) -> Plan | Refusal:
    """The seed's Session(): CheckCalibrate, CheckHome, CheckSession, then run. A check that
    fails sets its state (the table's Start row picks it), then ends this Start with a notice
    (the seed's "send WARNING…, stop session, send DONE"), and the reply says why."""
    target = start_checks(facts)  # the table's pick for Start's row
    if target is not S.RUNNING:
        return _refused(target, facts)
    session = facts.session
    assert session is not None  # the machine judges a Start's session
    rotate = m.keeper.calibration.rotate
    assert rotate is not None  # the checks passed: calibrated
    run = SessionRun(session, m.devices, m.live.current, rotate)
    return Plan(C.START, run, _session_done(m), f"Start session {session.name!r}", run)


def _refused(target: MachineState, facts: Facts) -> Refusal:
    """The check that failed (the table picked its state): how the Start ends, and why."""
    if target is S.WARNING_NEEDS_CALIBRATION:
        error: MachineError = NotCalibrated(
            f"Start refused: {' and '.join(facts.uncalibrated)} not calibrated"
        )
        return Refusal("Start: not calibrated", Outcome.REFUSED, error)
    if target is S.WARNING_NOT_HOME:
        missing = " and ".join(facts.not_home)
        error = NotHome(f"Start refused: {missing} not home; send Home first")
        return Refusal("Start: not home", Outcome.REFUSED, error)
    assert facts.bad_session is not None  # the pick chose FAULT_HW for it
    path, message = facts.bad_session
    fault = Fault(code=FaultCode.INVALID_SESSION, message=message)
    return Refusal("Start: bad session", Outcome.FAULT_HW, InvalidSession(message, path), fault)


def _session_done(m: Machine) -> OnDone:
    def done(now: float) -> Ending:
        m.go(Occurrence.MOTION_DONE, now, "session complete")
        return Ending(Outcome.DONE, "session complete")

    return done


def _its_own(command: Command) -> Handler:
    """A command whose transition is all it does (Pause, Resume, Stop): the machine's."""
    return lambda m, facts: command


def check_calibration(m: Machine, facts: Facts) -> Check:
    missing = facts.uncalibrated
    ok = not missing
    result = CheckResult(ok=ok, tilt="tilt" not in missing, rotate="rotate" not in missing)
    state = m.state
    if state in REST_STATES:
        if not ok and state is not S.WARNING_NEEDS_CALIBRATION:
            return Check(result, "CheckCalibration failed")
        if ok and state is S.WARNING_NEEDS_CALIBRATION:
            return Check(result, "CheckCalibration passed")
    return Check(result)


def check_home(m: Machine, facts: Facts) -> Check:
    missing = facts.not_home
    ok = not missing
    result = CheckResult(ok=ok, tilt="tilt" not in missing, rotate="rotate" not in missing)
    # Needing calibration is the bigger problem: that warning is not hidden (no row moves it).
    state = m.state
    if not ok and state in (S.IDLE, S.DONE):
        return Check(result, "CheckHome failed")
    if ok and state is S.WARNING_NOT_HOME:
        return Check(result, "CheckHome passed")
    return Check(result)


ACTIONS: dict[Command, Handler] = {
    C.CALIBRATE_TILT: calibrate_tilt,
    C.CALIBRATE_ROTATE: calibrate_rotate,
    C.HOME: home,
    C.START: start,
    C.PAUSE: _its_own(C.PAUSE),
    C.RESUME: _its_own(C.RESUME),
    C.STOP: _its_own(C.STOP),
    C.CHECK_CALIBRATION: check_calibration,
    C.CHECK_HOME: check_home,
}
"""One handler per command (its reply and kind: `table.HANDLING`)."""
