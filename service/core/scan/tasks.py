"""The work other threads hand the scan thread (`LoopPort.submit`): what each does there.

The bus builds these from what it heard and never reaches into the loop itself: each task runs
on the scan thread with the loop (`run`), or is refused if it never can (`reject`). They sit
above the loop (its inbox is typed by the loop they run with, `service/core/scan/inbox.py`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ride_machine.schema.calibration import CalibrationRecord, CalibrationSet
from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.errors import Error
from ride_machine.service.core.commands.identity import Identity
from ride_machine.service.errors import MachineError, Rejected

from .loop import ScanLoop
from .sink import calibration_record

if TYPE_CHECKING:
    from ride_machine.service.core.storage.persist import SaveTicket

log = logging.getLogger("machine")


@dataclass
class PendingCommand:
    """A decoded command waiting for the scan thread; `respond` takes its one reply (and
    must not wait: the bus hands it to a thread of its own to send)."""

    command: Command
    request: CommandRequest
    respond: Callable[[Reply], None]
    sender: str | None = None
    """The sending session's id, for the event history (the Rider attaches it)."""
    identity: Identity | None = None
    """`sender` once it confirmed the request (service/bus/confirm.py)."""

    def run(self, loop: ScanLoop, now: float) -> None:
        request, sender, identity = self.request, self.sender, self.identity
        self.respond(loop.execute(self.command, request, now, sender=sender, identity=identity))

    def reject(self, error: Error) -> None:
        self.respond(
            Reply.failure(
                error,
                transaction_id=self.request.transaction_id,
                command=self.command.value,
                timecode=time.time(),
                request_timecode=self.request.timecode,
            )
        )


@dataclass
class LoopCall:
    """Any work with the loop itself on the scan thread (tests, benchmarks, the demo)."""

    fn: Callable[[ScanLoop, float], None]
    on_reject: Callable[[Error], None] | None = None

    def run(self, loop: ScanLoop, now: float) -> None:
        self.fn(loop, now)

    def reject(self, error: Error) -> None:
        if self.on_reject is not None:
            self.on_reject(error)


@dataclass
class OnScanThread:
    """Work that must not race a cycle but reads nothing of the loop (a diagnostics reset, a
    simulator fault)."""

    fn: Callable[[], None]
    on_reject: Callable[[Error], None]

    def run(self, loop: ScanLoop, now: float) -> None:
        self.fn()

    def reject(self, error: Error) -> None:
        self.on_reject(error)


@dataclass
class Duplicates:
    """Other sessions hold this machine's id (`others`; empty: alone again)."""

    others: tuple[str, ...]
    own: str

    def run(self, loop: ScanLoop, now: float) -> None:
        loop.state_machine.duplicate_id(self.others, self.own, now)

    def reject(self, error: Error) -> None:
        pass  # the daemon is stopping: nothing moves any more


@dataclass
class RiderPresence:
    """A Rider's liveliness token came or went; only the controlling Rider's matters."""

    rider: str
    alive: bool

    def run(self, loop: ScanLoop, now: float) -> None:
        machine = loop.state_machine
        if machine.controller_rider != self.rider:
            return
        policy = loop.config.rider_loss.policy
        acted = False
        if self.alive:
            machine.rider_back()
        elif acted := machine.rider_lost(now):
            log.warning("event=rider_lost rider=%s policy=%s", self.rider, policy)
        loop.rider_event("rider_returned" if self.alive else "rider_lost", self.rider, acted, now)

    def reject(self, error: Error) -> None:
        pass


@dataclass
class EnterCalibration:
    """A technician's calibration values: used at once; `done` gets the record and the
    ticket of its write, `refused` the reason it was not taken."""

    values: CalibrationSet
    done: Callable[[CalibrationRecord, SaveTicket | None], None]
    refused: Callable[[MachineError], None]

    def run(self, loop: ScanLoop, now: float) -> None:
        try:
            ticket = loop.state_machine.enter_calibration(self.values, now)
        except MachineError as exc:
            self.refused(exc)
            return
        calibration = loop.state_machine.calibration
        self.done(calibration_record(calibration, loop.config.machine.id, now), ticket)

    def reject(self, error: Error) -> None:
        self.refused(Rejected(error))
