"""The sensors' signals judged in every full scan cycle, at rest as in motion: a value that no
state of the ride can give (a broken wire, a short) stops everything in the cycle it is read."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ride_machine.schema.status import FAULT_STATES
from ride_machine.service.core.motion.scale import signal_fault

if TYPE_CHECKING:
    from .machine import StateMachine


def judge_signals(machine: StateMachine, now: float) -> None:
    """The tilt's raw value where no tilt of the ride can put it (`signal_fault`): outputs off
    and FAULT_HW (`TILT_SIGNAL_RANGE`) before the state machine steps. Once: a machine in a
    fault state stays there until a command takes it out, and then meets this again."""
    if machine.state in FAULT_STATES:
        return
    fault = signal_fault(machine.devices.tilt.read_raw(), machine.live.current.tilt)
    if fault is not None:
        machine.devices.stop_all()
        machine.external_fault(fault, now, "tilt sensor", moved=machine.is_moving())
