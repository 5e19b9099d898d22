"""Each commanding OPC UA session supervises its motions like a Rider does.

The first command of an operator session declares a Rider of its own on the bus — a liveliness
token `rider/<login>/<key>/alive` and the deadman heartbeat `rider/<login>/<key>/heartbeat` (its
Zenoh login and a key of the session's own) — and names that
Rider in every command it sends. Both end when the session ends:

- the client closes its session (with or without Stop): the token goes, the machine applies
  its rider-loss policy at once;
- the client's link is frozen or cut: no request arrives for `session_timeout` seconds, the
  heartbeat stops, and the machine pauses `rider_loss.timeout_s` later.

So a motion started through OPC UA pauses within session timeout + rider-loss timeout (plus
one `CHECK_S`) of its client's last request (docs/plant.md).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any, Protocol

from ride_machine.schema.rider import rider_id

from .security import Caller
from .uaserver import open_sessions

log = logging.getLogger(__name__)

CHECK_S = 0.1
"""How often the sessions that supervise are looked at."""


class Closable(Protocol):
    def close(self) -> None: ...


Declare = Callable[[str, str], Closable]
"""Declares the Rider `key` on the bus for the OPC UA user named (blocking; the machine records
that user as who commanded); closing it undeclares it."""


class Supervisor:
    """The Riders of the OPC UA sessions that commanded, and the watch that ends them."""

    def __init__(
        self,
        declare: Declare,
        open_sessions: Callable[[], set[str]],
        session_timeout: float,
        clock: Callable[[], float] = time.monotonic,
        login: str = "anonymous",
    ) -> None:
        """`login`: the gateway's Zenoh login, the first part of its Riders' ids
        (`<login>/<key>`, schema.rider): the machine refuses a bare key (schema 1)."""
        self._declare = declare
        self._login = login
        self._open_sessions = open_sessions
        self.session_timeout = session_timeout
        self._clock = clock
        self._riders: dict[str, tuple[Caller, Closable]] = {}
        self._lock = asyncio.Lock()

    @property
    def supervising(self) -> int:
        return len(self._riders)

    async def rider_for(self, caller: Caller) -> str:
        """The caller's Rider id (`<login>/<key>`), declared on first use."""
        rider = rider_id(self._login, caller.key)
        async with self._lock:
            if caller.key not in self._riders:
                handle = await asyncio.to_thread(self._declare, rider, caller.name)
                self._riders[caller.key] = (caller, handle)
                log.info("event=opcua_rider_declared rider=%s user=%s", rider, caller.name)
        return rider

    def gone(self) -> list[str]:
        """The Riders whose session closed or went quiet past the session timeout."""
        open_now = self._open_sessions()
        now = self._clock()
        return [
            key
            for key, (caller, _) in self._riders.items()
            if key not in open_now or now - caller.last_active > self.session_timeout
        ]

    async def end(self, keys: list[str], reason: str = "session_gone") -> None:
        for key in keys:
            caller, handle = self._riders.pop(key)
            await asyncio.to_thread(handle.close)
            idle = self._clock() - caller.last_active
            log.warning("event=opcua_rider_ended rider=%s reason=%s idle_s=%.3f", key, reason, idle)

    async def watch(self) -> None:
        """Ends the Riders of sessions gone, every `CHECK_S`, until cancelled."""
        while True:
            await asyncio.sleep(CHECK_S)
            if gone := self.gone():
                async with self._lock:
                    await self.end([k for k in gone if k in self._riders])

    async def close(self) -> None:
        async with self._lock:
            await self.end(list(self._riders), "gateway_stopped")


def open_session_keys(iserver: Any) -> set[str]:
    """The keys of the OPC UA sessions open now."""
    return {s.user.key for s in open_sessions(iserver) if isinstance(s.user, Caller)}
