"""The calibration keeper: the calibration in use (measured when its motion ends, or a
technician's entered by hand), the write that persists it, and which axes have a reference.

A calibration is used at once; its motion ends (and the table's `SAVED` row leaves
CALIBRATING) only once the disk has answered, so the notice says whether it was saved. The
keeper says what happened; the state machine makes the state change.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ride_machine.schema.calibration import CalibrationSet
from ride_machine.schema.completion import Outcome
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import AxesFlags, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.calibrate import RotateCalibrate, TiltCalibrate
from ride_machine.service.core.motion.devices import Calibration, Devices
from ride_machine.service.core.motion.manual import manual_calibration
from ride_machine.service.errors import WrongState

from .context import Ending, Motion

if TYPE_CHECKING:  # types only: the state machine does no IO
    from ride_machine.service.core.storage.persist import SaveTicket

AXES_OFF: dict[tuple[bool, bool], tuple[str, ...]] = {
    (tilt, rotate): ("tilt",) * tilt + ("rotate",) * rotate
    for tilt in (False, True)
    for rotate in (False, True)
}
"""The axes named by (tilt, rotate) flags, in that order: the guards' tuples, made once."""
COMPLETE = "calibration complete"

OnCalibrated = Callable[[Calibration], "SaveTicket | None"]
"""Persist a new calibration; a ticket that is not done keeps CALIBRATING until it is."""


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


@dataclass(frozen=True, slots=True)
class Saved:
    """A write that ended: how its motion ended, the transition's reason, and that motion."""

    ending: Ending
    why: str
    motion: Motion | None


class CalibrationKeeper:
    """The calibration in use, its write, and the axes' references."""

    def __init__(
        self, calibration: Calibration, devices: Devices, on_calibrated: OnCalibrated | None
    ) -> None:
        self.devices = devices
        self.on_calibrated = on_calibrated
        self.calibration = calibration
        devices.tilt.calibration = calibration.tilt
        self.refs = Refs()
        self.saving: Saving | None = None
        self.save_ticket: SaveTicket | None = None
        """The write of the calibration in use (None: nothing to write it to, or not yet)."""

    def homed(self) -> AxesFlags:
        """An axis is home when it has a reference and its home switch is closed now."""
        tilt, rotate = self._home()
        return AxesFlags(tilt=tilt, rotate=rotate)

    def _home(self) -> tuple[bool, bool]:
        """(tilt, rotate): each has a reference and its home switch is closed now."""
        refs, devices = self.refs, self.devices
        return refs.tilt and devices.tilt.is_home(), refs.rotate and devices.rotate.is_home()

    def not_home(self) -> tuple[str, ...]:
        """The axes `homed` says are not (without making its flags: read per command)."""
        tilt, rotate = self._home()
        return AXES_OFF[not tilt, not rotate]

    def uncalibrated(self) -> tuple[str, ...]:
        """The axes without a calibration."""
        cal = self.calibration
        return AXES_OFF[cal.tilt is None, cal.rotate is None]

    def lose_references(self) -> None:
        """A hardware fault while moving: neither axis is trusted until homed again."""
        self.refs.tilt = self.refs.rotate = False

    def homed_both(self) -> None:
        """A Home (or a rotate calibration, which homes both) ended: both axes referenced."""
        self.refs.tilt = self.refs.rotate = True

    def tilt_measured(self, ctl: TiltCalibrate, wall: float, motion: Motion | None) -> bool:
        """CalibrateTilt ended: the tilt's zero is its reference now. True: the motion is
        done; False: it waits for the write (`saved`)."""
        assert ctl.result is not None  # it finished DONE
        self.refs.tilt = True
        tilt = dataclasses.replace(ctl.result, at=wall)
        return self._measured(Calibration(tilt=tilt, rotate=self.calibration.rotate), motion)

    def rotate_measured(self, ctl: RotateCalibrate, wall: float, motion: Motion | None) -> bool:
        """CalibrateRotate ended (both axes were homed on the way); as `tilt_measured`."""
        assert ctl.result is not None  # it finished DONE
        self.homed_both()
        rotate = dataclasses.replace(ctl.result, at=wall)
        return self._measured(Calibration(tilt=self.calibration.tilt, rotate=rotate), motion)

    def verified(self) -> None:
        """When a motion ends (done or faulted): an entered calibration its stroke verified
        (`TiltVerify`) is the machine's calibration now, shown verified (not saved: a start
        verifies an entered one again). A Home whose rotate part failed after the tilt's
        verification keeps the verification."""
        tilt, mine = self.devices.tilt.calibration, self.calibration.tilt
        if tilt is None or mine is None or tilt is mine or not tilt.verified or mine.verified:
            return
        if dataclasses.replace(tilt, verified=False) == mine:
            self.calibration = dataclasses.replace(self.calibration, tilt=tilt)

    def entered(
        self,
        values: CalibrationSet,
        config: MachineConfig,
        wall: float,
        state: MachineState,
        busy: bool,
    ) -> SaveTicket | None:
        """A technician's values, recorded as manual: validated against the same plausible
        ranges a measurement must meet, used at once and persisted (the ticket of the write);
        refused while a motion is under way (`busy`, in `state`) or a calibration is saved."""
        if busy or self.saving is not None:
            raise WrongState(
                f"calibration values cannot be entered in state {state} while a motion"
                " is under way (or its calibration is being saved); Stop it first"
            )
        cal = manual_calibration(values, config, self.calibration, wall)
        # Not trusted until a Home has checked it with a measured move (docs/homing.md).
        self.refs.tilt &= values.tilt is None
        self.refs.rotate &= values.rotate is None
        return self._use(cal)

    def written(self) -> bool:
        """The write a calibration's motion waits for has ended (`saved` says how)."""
        return self.saving is not None and self.saving.ticket.done

    def saved(self) -> Saved:
        """The write has ended: how the motion that waited for it ended."""
        assert self.saving is not None
        ticket, motion = self.saving.ticket, self.saving.motion
        self.saving = None
        problem = ticket.problem
        if problem:
            ending = Ending(Outcome.STORAGE_FAILED, problem, ErrorCode.STORAGE_FAILED.value)
            return Saved(ending, COMPLETE + ", NOT saved", motion)
        return Saved(Ending(Outcome.DONE, COMPLETE), COMPLETE, motion)

    def _measured(self, cal: Calibration, motion: Motion | None) -> bool:
        """Use `cal` now and persist it: True if there is nothing to wait for."""
        ticket = self._use(cal)
        if ticket is None:
            return True
        # Still CALIBRATING (outputs off, no controller) until the disk answers: a Rider that
        # waits for the calibration learns whether it was saved from the notice that ends it.
        self.saving = Saving(ticket, motion)
        return False

    def _use(self, cal: Calibration) -> SaveTicket | None:
        """Use `cal` from now on and persist it (the ticket of the write, if any)."""
        self.calibration = cal
        self.devices.tilt.calibration = cal.tilt
        ticket = self.on_calibrated(cal) if self.on_calibrated is not None else None
        self.save_ticket = ticket
        return ticket
