"""`Outbox`: the replies work on the scan thread makes, sent from a thread of their own.

The scan thread never sends a reply itself, because a reply can wait. Since Zenoh 1.8
(eclipse-zenoh/zenoh#2382) a reply, an error reply and the query's end (`ResponseFinal`, sent as
the query is dropped) all take the query's own QoS, and a `get` blocks by default: toward an
asker whose link is full (it stopped reading) they wait, up to `transport/link/tx/queue/
congestion_control/block/wait_before_close` (Zenoh's 5 s; 0.25 s in this project's configs,
common/zenoh_session.py, BLOCK_WAIT_US). The replier cannot choose otherwise
(`Query.reply`'s `congestion_control` is deprecated and ignored). On the scan thread that wait
would stop the scan, and the watchdog would take FAULT_HW. A reply dropped because too many
wait already is safe: a command runs at most once per `transaction_id`, and a Rider that hears
nothing asks again.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import zenoh
from pydantic import BaseModel

from ride_machine.service.errors import MachineError

from .deferred import Deferred
from .request import Request

log = logging.getLogger(__name__)

OUTBOX_MAX = 1024
"""Replies waiting at most (the scan thread's inbox holds as many tasks); beyond, one is dropped."""
OUTBOX_THREAD = "reply-out"


class Outbox:
    """Sends replies in the order they were handed over, on a thread started for them."""

    def __init__(self, capacity: int = OUTBOX_MAX) -> None:
        self._jobs = Deferred(capacity, name=OUTBOX_THREAD)

    def later(self, send: Callable[[], None], key: str) -> None:
        """Queue `send` (one reply to a query on `key`); never waits. With `capacity` replies
        waiting already (their links are full), it is dropped, and said so."""
        if not self._jobs.put(send):
            log.warning("event=reply_dropped key=%s reason=outbox_full", key)

    def reply(
        self,
        request: Request,
        model: BaseModel,
        key: str | zenoh.KeyExpr | None = None,
        packed: bytes | None = None,
    ) -> None:
        """`request.reply(model, key, packed)`, sent from the outbox's thread."""
        self.later(functools.partial(request.reply, model, key, packed), request.key)

    def refuse(self, request: Request, error: MachineError) -> None:
        """`request.refuse(error)`, sent from the outbox's thread."""
        self.later(functools.partial(request.refuse, error), request.key)

    def drain(self, timeout: float) -> bool:
        """Wait until every reply handed over so far has gone (before the session closes)."""
        return self._jobs.drain(timeout)
