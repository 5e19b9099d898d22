"""Queries that change the machine but are not commands: parameters, calibration entered by
hand, and the diagnostics reset. A write names one key of one machine (no wildcards)."""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from pydantic import BaseModel

from ride_machine.schema.calibration import CalibrationRecord, CalibrationSet
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import Error
from ride_machine.schema.events import ParamEvent
from ride_machine.schema.params import ParamSet, ParamValue
from ride_machine.service.adapters.eventlog import EventLog
from ride_machine.service.core.commands.identity import Identity
from ride_machine.service.core.scan.port import LoopPort
from ride_machine.service.core.scan.tasks import EnterCalibration, OnScanThread
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.storage.persist import SaveTicket
from ride_machine.service.core.storage.safety import is_safety
from ride_machine.service.errors import BadRequest, Busy, MachineError, Rejected, StorageFailed
from ride_machine.service.threads import NamedThread

from .confirm import Confirmer
from .outbox import Outbox
from .reads import matching
from .request import Request, sender_of
from .routes import Route, Wildcard

log = logging.getLogger(__name__)

SAVE_WAIT_S = 5.0
"""How long a manual calibration write may take before its reply says it was not saved."""


class ParamService(Protocol):
    """What the bus needs from the parameter registry (service/core/storage/params.py)."""

    def list(self) -> list[ParamValue]: ...

    def get(self, name: str) -> ParamValue: ...

    def set(self, name: str, req: ParamSet, *, moving: bool, now: float) -> ParamValue: ...


def on_scan_thread(
    port: LoopPort, outbox: Outbox, request: Request, make: Callable[[], BaseModel]
) -> None:
    """Run `make` on the scan thread, between or within cycles; `outbox` answers `request`
    with what it made, or refuses it with the `MachineError` it raised (or because it never
    ran): the scan thread sends no reply itself (service/bus/outbox.py)."""

    def run() -> None:
        try:
            model = make()
        except MachineError as exc:
            outbox.refuse(request, exc)
            return
        outbox.reply(request, model)

    def rejected(error: Error) -> None:
        outbox.refuse(request, Rejected(error))

    if not port.submit(OnScanThread(run, rejected)):
        raise Busy("command queue full; retry later")


RELEASE_TIMEOUT_S = 0.05
"""How long a write waits for the loop's lock to hand over the commands it holds."""


@dataclass
class Writes:
    """The daemon's write routes other than commands."""

    base: str
    port: LoopPort
    stats: CycleStats
    diag: Callable[[], CycleDiag]
    wall: Callable[[], float]
    params: ParamService | None = None
    events: EventLog | None = None
    confirmer: Confirmer | None = None
    outbox: Outbox = field(default_factory=Outbox)
    """Sends the replies of work done on the scan thread."""

    def routes(self) -> list[Route]:
        named = Wildcard.REFUSE_NAMED
        routes = [
            Route(
                "diag/reset", self.reset, named, what="a diagnostics reset", example="diag/reset"
            ),
            Route(
                "calibration/set",
                self.calibration,
                named,
                sniff=True,
                what="a calibration write",
                example="calibration/set",
            ),
        ]
        if self.params is not None:
            routes.append(
                Route(
                    "params/**",
                    self.param,
                    Wildcard.REFUSE_WRITES,
                    sniff=True,
                    what="a parameter write",
                    example="params/<name>",
                )
            )
        return routes

    def reset(self, request: Request) -> None:
        """Reply with the counters as they were, reset on the scan thread before the reply
        leaves (a read sent on the reply's heels sees the reset, not the counters before it)."""

        def reset() -> CycleDiag:
            before = self.diag()
            self.stats.reset(self.wall())
            return before

        on_scan_thread(self.port, self.outbox, request, reset)

    def param(self, request: Request) -> None:
        params = self.params
        assert params is not None
        name = request.key[len(f"{self.base}/params/") :]
        # Reads never touch the scan thread: the registry hands out immutable values.
        if request.wild:  # a read: the route refused a wildcard write
            matching(request, self.base, [(f"params/{p.name}", p) for p in params.list()])
            return
        if not request.payload:
            request.reply(params.get(name))
            return
        req = request.decode(ParamSet)
        # The registry is thread-safe and its write (with fsync) stays off the scan thread;
        # the loop picks the new config up at the next cycle boundary.
        old = params.get(name)
        by = sender_of(request.query)
        record = functools.partial(self._record, old, req, by, self._confirmed(by, request))
        try:
            value = params.set(name, req, moving=self.port.moving(), now=self.wall())
        except MachineError as exc:
            if is_safety(old.name):  # every try at a safety setting is on the record
                record(old.default if req.reset else req.value, False, exc.message)
            raise
        record(value.value, value.persisted, "")
        request.reply(value)

    def _record(
        self,
        old: ParamValue,
        req: ParamSet,
        by: str | None,
        identity: Identity | None,
        new: object,
        persisted: bool,
        refused: str,
    ) -> None:
        if self.events is None:
            return
        kind = "safety_changed" if is_safety(old.name) else "param_changed"
        # The commands answered before this write are in the history before it (the loop
        # holds them for its next cycle), as a history read sees them (reads.py).
        self.port.release_records(RELEASE_TIMEOUT_S)
        self.events.emit_now(
            ParamEvent(
                kind=kind,
                name=old.name,
                old=old.value,
                new=_recordable(new),
                persisted=persisted,
                reset=req.reset,
                transaction_id=req.transaction_id,
                by=by,
                identity=identity.rider if identity else None,
                operator=identity.operator if identity else None,
                accepted=not refused,
                message=refused,
            )
        )

    def _confirmed(self, by: str | None, request: Request) -> Identity | None:
        """`by` once that Rider confirmed the write (asked on this route's own thread, never
        Zenoh's); None: nobody named, or only claimed. A write is not refused for it."""
        if by is None or self.confirmer is None:
            return None
        return self.confirmer.ask(by, request.payload).identity(by)

    def calibration(self, request: Request) -> None:
        """Values entered by hand: applied on the scan thread, answered once they are saved."""
        if not request.payload:
            raise BadRequest(
                'send {"transaction_id": "…", "tilt": {"offset_counts": …,'
                ' "gain_counts_per_deg": …}} and/or "rotate": {"revolution_s": …,'
                ' "home_arc_deg": …}',
                path="/transaction_id",
            )
        req = request.decode(CalibrationSet)

        def entered(record: CalibrationRecord, ticket: SaveTicket | None) -> None:
            """On the scan thread: the values are in use; a short-lived thread answers once
            they are saved (the scan thread never waits for the disk)."""
            log.info(
                "event=calibration_entered tx=%s timecode=%s tilt=%s rotate=%s",
                req.transaction_id,
                req.timecode,
                req.tilt is not None,
                req.rotate is not None,
            )
            record = record.model_copy(update={"time": self.wall()})
            NamedThread(
                target=_answer_saved,
                args=(request, record, ticket),
                name="calibration-saved",
                daemon=True,
            ).start()

        refused = functools.partial(self.outbox.refuse, request)  # the scan thread never sends
        if not self.port.submit(EnterCalibration(req, entered, refused)):
            raise Busy("command queue full; retry later")


def _answer_saved(request: Request, record: CalibrationRecord, ticket: SaveTicket | None) -> None:
    problem = None
    if ticket is not None:
        problem = ticket.problem if ticket.wait(SAVE_WAIT_S) else "the write did not finish"
    if problem is not None:
        request.refuse(
            StorageFailed(f"calibration entered and in use now, but NOT saved: {problem}")
        )
        return
    request.reply(record)


_INT64 = range(-(2**63), 2**64)
"""The integers msgpack carries (int64 and uint64)."""


def _recordable(value: object) -> bool | int | float | str:
    """A written value as the history keeps it: an integer msgpack cannot carry (a refused
    write of 310 digits) in words, since every read and sample of the history is msgpack."""
    if isinstance(value, int) and not isinstance(value, bool) and value not in _INT64:
        return f"an integer of {value.bit_length()} bits"
    return value if isinstance(value, bool | int | float | str) else repr(value)
