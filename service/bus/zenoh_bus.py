"""One machine on Zenoh: its route table, publications and presence, declared together.

Built after the scan loop, from what the loop offers other threads (`LoopPort`) and the sink the
loop publishes to (`Publications`, made before the loop): the bus never reads the loop itself.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any

from pydantic import BaseModel

from ride_machine.schema.status import MachineState
from ride_machine.service.core.scan.port import LoopPort

from .commands import Commands
from .confirm import Confirmer
from .injection import Injection, SimPort
from .outbox import Outbox
from .presence import Presence
from .publications import Publications
from .reads import ConfigChecker, Reads
from .request import Request
from .routes import Route, declare
from .writes import ParamService, Writes, on_scan_thread

log = logging.getLogger("service.bus")

OUTBOX_DRAIN_S = 1.0
"""How long a closing bus waits for the replies handed over to go (toward an asker whose link is
full a reply may wait; the stop does not wait for it longer than this)."""


class ZenohBus:
    """Puts one machine on Zenoh under `<key_prefix>/<id>`: its queryables and presence over
    the loop's port, its publications through the loop's sink."""

    def __init__(
        self,
        port: LoopPort,
        publications: Publications,
        *,
        io_keys: Iterable[str],
        sim: SimPort | None = None,
        params: ParamService | None = None,
        check_config: ConfigChecker | None = None,
        sim_elsewhere: bool = False,
    ) -> None:
        """`publications`: the loop's sink, with the session, config and diagnostics they
        share; `io_keys`: the IO points' keys (`io/<kind>/<name>`), declared up front;
        `sim_elsewhere`: another session (the supervisor) answers `sim/**` for this machine."""
        self.port = port
        self.publications = pubs = publications
        self.session = session = pubs.session
        config, events = pubs.config, pubs.events
        self.base = b = config.key_base
        self.wall = wall = pubs.wall
        self.io_keys = tuple(io_keys)
        self.presence = Presence(session, port, config)
        confirmer = Confirmer(session, config.bus.confirm_timeout_s)
        self.outbox = outbox = Outbox()
        """Sends the replies of work done on the scan thread, which never sends one."""
        routes: list[Route] = [
            *Commands(b, port, confirmer, events, outbox).routes(),
            *Reads(b, port, pubs.diag, check_config=check_config, events=events).routes(),
            *Writes(
                b,
                port,
                pubs.stats,
                pubs.diag,
                wall,
                params=params,
                events=events,
                confirmer=confirmer,
                outbox=outbox,
            ).routes(),
        ]
        # Declared without a simulator too: `sim/*` on real hardware answers NOT_AVAILABLE
        # at once instead of leaving the caller to time out (a supervisor answers for its child).
        if sim is not None or not sim_elsewhere:
            routes += Injection(b, sim, config.hal.backend, self._on_scan_thread, wall).routes()
        self.routes = routes
        self._declared: list[Any] = []

    def state(self) -> MachineState | None:
        """`Host`: the state a refusal states (the last one published)."""
        status = self.port.published().status
        return status.state if status is not None else None

    def _on_scan_thread(self, request: Request, make: Callable[[], BaseModel]) -> None:
        on_scan_thread(self.port, self.outbox, request, make)

    @property
    def others(self) -> set[str]:
        """Other sessions that hold this machine's id: duplicates."""
        return self.presence.others

    def publish_watchdog_trip(self, stalled_s: float) -> None:
        """From the watchdog thread: FAULT_HW at once, the scan thread may be stuck."""
        self.publications.publish_watchdog_trip(stalled_s)

    def start(self) -> None:
        """Declare queryables and publishers, start the diag publisher; the liveliness token
        follows with the first status (`Publications.publish_status`)."""
        s = self.session
        self.publications.hold()
        self._declared += declare(s, self.base, self, self.routes)
        self._declared += self.publications.declare(self.io_keys)
        self._declared += self.presence.declare()
        log.info("event=bus_started base=%s zid=%s", self.base, s.zid())

    def close(self) -> None:
        """Send the replies still handed over (the last answers of a stop), then undeclare
        everything (the session itself is closed by its owner)."""
        if not self.outbox.drain(OUTBOX_DRAIN_S):
            log.warning("event=replies_unsent timeout_s=%g", OUTBOX_DRAIN_S)
        self.publications.undeclare()
        for entity in reversed(self._declared):
            entity.undeclare()
        self._declared.clear()
