"""This Rider's word for its own requests: `rider/<login>/<zid>/confirm`.

Before it binds a ride to a Rider (its deadman) or records a Rider as the sender of a request, the
machine asks the Rider named in it whether it sent that request (schema/rider.py, `digest`). The
Rider keeps the digests of the requests it sent (`Ledger`) and answers from them: a station that
copies another's Rider id into a request of its own gets a "no" from the Rider it named.
"""

from __future__ import annotations

import contextlib
import threading
from collections import OrderedDict
from typing import Any

import zenoh

from ride_machine.schema.rider import (
    CONFIRM_QUERY_BYTES,
    DENIED,
    LEDGER_SIZE,
    confirm_key,
    confirmation,
    digest,
)


class Ledger:
    """The digests of the last `size` requests this Rider sent (thread-safe)."""

    def __init__(self, size: int = LEDGER_SIZE) -> None:
        self.size = size
        self._sent: OrderedDict[bytes, None] = OrderedDict()
        self._lock = threading.Lock()

    def sent(self, payload: bytes) -> None:
        """Note `payload` as sent (before it goes: the machine may ask at once)."""
        key = digest(payload)
        with self._lock:
            self._sent[key] = None
            self._sent.move_to_end(key)
            while len(self._sent) > self.size:
                self._sent.popitem(last=False)

    def knows(self, key: bytes) -> bool:
        with self._lock:
            return key in self._sent


class Confirmations:
    """The queryable that answers the machine's confirmation queries from a `Ledger`."""

    def __init__(
        self, session: zenoh.Session, rider_id: str, ledger: Ledger, operator: str | None = None
    ) -> None:
        """`operator`: the person this Rider acts for, named in each confirmation (the plant
        gateway's OPC UA user; None for a Rider whose person the bus knows by its login)."""
        self.ledger = ledger
        self._yes = confirmation(operator)
        self._queryable: Any = session.declare_queryable(  # its undeclare has no types
            confirm_key(rider_id), self._answer
        )

    def _answer(self, query: zenoh.Query) -> None:
        payload = query.payload
        key = payload.to_bytes() if payload is not None else b""
        known = len(key) == CONFIRM_QUERY_BYTES and self.ledger.knows(key)
        with query, contextlib.suppress(zenoh.ZError):  # the asker may be gone already
            query.reply(query.key_expr, self._yes if known else DENIED)

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self._queryable.undeclare()
