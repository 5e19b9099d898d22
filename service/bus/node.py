"""One machine on Zenoh: its route table, publications and presence, declared together."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import zenoh

from schema.status import MachineState
from service.adapters.eventlog import EventLog
from service.bus.commands import Commands
from service.bus.injection import Injection, SimPort
from service.bus.presence import Presence
from service.bus.publications import Publications
from service.bus.reads import ConfigChecker, Reads
from service.bus.request import Request
from service.bus.routes import Route, declare
from service.bus.writes import ParamService, Writes, on_loop
from service.config.model import MachineConfig
from service.core.loop import ScanLoop
from service.core.timing import CycleStats

log = logging.getLogger("service.bus")


class ZenohBus(Publications):
    """Puts one machine on Zenoh under `<key_prefix>/<id>`; implements the loop's `LoopSink`."""

    def __init__(  # noqa: PLR0913 - four parts, then keyword-only options
        self,
        session: zenoh.Session,
        loop: ScanLoop,
        stats: CycleStats,
        config: MachineConfig,
        *,
        sim: SimPort | None = None,
        params: ParamService | None = None,
        check_config: ConfigChecker | None = None,
        wall: Callable[[], float] = time.time,
        clock: Callable[[], float] = time.monotonic,
        events: EventLog | None = None,
        sim_elsewhere: bool = False,
    ) -> None:
        """`sim_elsewhere`: another session (the supervisor) answers `sim/**` for this machine."""
        super().__init__(session, loop, stats, config, wall, events)
        self.clock = clock
        """The scan loop's clock (the runner's), for commands run between cycles."""
        self.presence = Presence(session, loop, config, clock)
        b = self.base
        routes: list[Route] = [
            *Commands(b, loop, clock).routes(),
            *Reads(b, loop, self.diag, check_config=check_config, events=events).routes(),
            *Writes(
                b, loop, stats, self.diag, config.machine.id, wall, params=params, events=events
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
        status = self.loop.published.status
        return status.state if status is not None else None

    def _on_scan_thread(self, request: Request, fn: Callable[[], None]) -> None:
        on_loop(self.loop, request, lambda loop, now: fn())

    @property
    def others(self) -> set[str]:
        """Other sessions that hold this machine's id: duplicates."""
        return self.presence.others

    def start(self) -> None:
        """Declare queryables and publishers, start the diag publisher; the liveliness token
        follows with the first status (`publish_status`)."""
        s = self.session
        self.hold()
        self._declared += declare(s, self.base, self, self.routes)
        self._declared += self.declare()
        self._declared += self.presence.declare()
        self.loop.beats = self.presence
        log.info("event=bus_started base=%s zid=%s", self.base, s.zid())

    def close(self) -> None:
        """Undeclare everything (the session itself is closed by its owner)."""
        self.undeclare()
        for entity in reversed(self._declared):
            entity.undeclare()
        self._declared.clear()
