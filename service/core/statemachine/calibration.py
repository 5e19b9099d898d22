"""Calibration: a measured one when its motion ends, a technician's entered by hand, and the
write that persists it. A calibration is used at once; its motion ends (and the table's
`SAVED` row leaves CALIBRATING) only once the disk has answered, so the notice says whether
it was saved.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from schema.calibration import CalibrationSet
from schema.commands import REST_STATES
from schema.completion import Outcome
from schema.errors import ErrorCode
from schema.status import MachineState
from service.core.calibrate import RotateCalibrate, TiltCalibrate
from service.core.devices import Calibration
from service.core.manual import manual_calibration
from service.core.statemachine.context import Ending, Saving
from service.core.statemachine.table import Event
from service.errors import WrongState

if TYPE_CHECKING:
    from service.core.persist import SaveTicket
    from service.core.statemachine.machine import StateMachine

S = MachineState
COMPLETE = "calibration complete"


def tilt_measured(m: StateMachine, ctl: TiltCalibrate, now: float) -> Ending | None:
    """CalibrateTilt's `on_done`: the tilt's zero is its reference now."""
    assert ctl.result is not None  # it finished DONE
    m.refs.tilt = True
    tilt = dataclasses.replace(ctl.result, at=now + m.wall_offset)
    return _measured(m, Calibration(tilt=tilt, rotate=m.calibration.rotate), now)


def verified(m: StateMachine) -> None:
    """When a motion ends (done or faulted): an entered calibration its stroke verified
    (`TiltVerify`) is the machine's calibration now, shown verified (not saved: a start
    verifies an entered one again). A Home whose rotate part failed after the tilt's
    verification keeps the verification."""
    tilt, mine = m.devices.tilt.calibration, m.calibration.tilt
    if tilt is None or mine is None or tilt is mine or not tilt.verified or mine.verified:
        return
    if dataclasses.replace(tilt, verified=False) == mine:
        m.calibration = dataclasses.replace(m.calibration, tilt=tilt)


def rotate_measured(m: StateMachine, ctl: RotateCalibrate, now: float) -> Ending | None:
    """CalibrateRotate's `on_done`: both axes were homed on the way."""
    assert ctl.result is not None  # it finished DONE
    m.refs.tilt = m.refs.rotate = True
    rotate = dataclasses.replace(ctl.result, at=now + m.wall_offset)
    return _measured(m, Calibration(tilt=m.calibration.tilt, rotate=rotate), now)


def enter(m: StateMachine, values: CalibrationSet, now: float) -> SaveTicket | None:
    """A technician's values, recorded as manual: validated against the same plausible
    ranges a measurement must meet, refused while a motion is under way, then used at once
    and persisted (the ticket says when the write is done, and how)."""
    if m.is_moving() or m.action is not None or m.saving is not None:
        raise WrongState(
            f"calibration values cannot be entered in state {m.state} while a motion"
            " is under way (or its calibration is being saved); Stop it first"
        )
    cal = manual_calibration(values, m.config, m.calibration, now + m.wall_offset)
    # Not trusted until a Home has checked it with a measured move (docs/homing.md).
    m.refs.tilt &= values.tilt is None
    m.refs.rotate &= values.rotate is None
    ticket = _use(m, cal)
    if m.state in REST_STATES and m.state is not S.DONE:
        m.go(Event.CALIBRATION_ENTERED, now, "calibration entered by hand")
    return ticket


def save_done(m: StateMachine, saving: Saving, now: float) -> None:
    """A background save finished: the calibration waiting for it (if any) has ended."""
    ending = _saved(m, saving.ticket, now)
    if m.action is not None and m.action is saving.motion:
        m.end(ending, now)


def _use(m: StateMachine, cal: Calibration) -> SaveTicket | None:
    """Use `cal` from now on and persist it (the ticket of the write, if any)."""
    m.calibration = cal
    m.devices.tilt.calibration = cal.tilt
    ticket = m.on_calibrated(cal) if m.on_calibrated is not None else None
    m.save_ticket = ticket
    return ticket


def _measured(m: StateMachine, cal: Calibration, now: float) -> Ending | None:
    """Use `cal` now and persist it; it has ended once the write has (None until then)."""
    ticket = _use(m, cal)
    if ticket is None:
        m.go(Event.MOTION_DONE, now, COMPLETE)
        return Ending(Outcome.DONE, COMPLETE)
    # Still CALIBRATING (outputs off, no controller) until the disk answers: a Rider that
    # waits for the calibration learns whether it was saved from the notice that ends it.
    m.saving = Saving(ticket, m.action)
    if ticket.done:
        return _saved(m, ticket, now)
    return None


def _saved(m: StateMachine, ticket: SaveTicket, now: float) -> Ending:
    m.saving = None
    problem = ticket.problem
    if problem:
        ending = Ending(Outcome.STORAGE_FAILED, problem, ErrorCode.STORAGE_FAILED.value)
    else:
        ending = Ending(Outcome.DONE, COMPLETE)
    if m.state is S.CALIBRATING and m.drive.controller is None:
        m.go(Event.SAVED, now, COMPLETE + (", NOT saved" if problem else ""))
    return ending
