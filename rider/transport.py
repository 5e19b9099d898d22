"""The Rider's queries: every reply to a key (two daemons with one id must both be seen), vetted
for who sent it (`Pinning`), then decoded (`rider.replies`)."""

from __future__ import annotations

import time

import zenoh

from .errors import MachineTimeout
from .link import Link, bus_error
from .pinning import Pinning
from .replies import MSGPACK, M, decode_ok, decode_reply, zenoh_timeout

EMPTY_RETRY_S = 0.05
_ALL = zenoh.ConsolidationMode.NONE


class Transport:
    """Queries on this Rider's link, their replies vetted by `pins`."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.pins = Pinning(link)

    def get_one(self, key: str, payload: bytes | None, model: type[M], timeout: float | None) -> M:
        """The first reply. An empty answer that comes back early means no queryable was
        matched yet (a peer's declarations still on their way just after open): ask again
        until the timeout. Safe for commands too: the transaction id makes them at-most-once."""
        limit = timeout or self.link.timeout
        deadline = time.monotonic() + limit
        while True:
            remaining = deadline - time.monotonic()
            replies = self.get(key, payload, max(remaining, 0.05))
            if len(replies) == 1:  # the usual answer: one reply, from the machine, ok
                sample = replies[0].ok
                if sample is not None:
                    return decode_ok(sample, model)
            replies = self.answered(key, replies, limit)
            if replies:
                return decode_reply(replies[0], model)
            if deadline - time.monotonic() < EMPTY_RETRY_S:
                hint = self.link.no_link_hint() or " (is the machine up?)"
                raise MachineTimeout(f"no reply from {key} within {limit:g} s{hint}")
            time.sleep(EMPTY_RETRY_S)

    def get_all(self, key: str, model: type[M], *, required: bool = True) -> list[M]:
        """Every reply to a wildcard key. `required`: a live machine always answers it (IO,
        axes, parameters), so no reply at all is `MachineTimeout`, never an empty list."""
        timeout = self.link.timeout
        replies = self.answered(key, self.get(key, None, None), timeout)
        if required and not replies:
            hint = self.link.no_link_hint() or " (is the machine up?)"
            raise MachineTimeout(f"no reply from {key} within {timeout:g} s{hint}")
        return [decode_reply(r, model) for r in replies]

    @staticmethod
    def answered(key: str, replies: list[zenoh.Reply], limit: float) -> list[zenoh.Reply]:
        """The replies a queryable sent. A query that reached one (a frozen or stalled daemon,
        a router forwarding to it) but got no answer in time ends with Zenoh's own error reply
        `Timeout`: that is no reply, never the machine's refusal."""
        answered = [r for r in replies if not zenoh_timeout(r)]
        if replies and not answered:
            raise MachineTimeout(
                f"no reply from {key} within {limit:g} s: the machine was reached but did not"
                " answer (frozen or overloaded?)"
            )
        return answered

    def get(self, key: str, payload: bytes | None, timeout: float | None) -> list[zenoh.Reply]:
        """All replies to `key` (asked by its key expression when it is declared), vetted."""
        link = self.link
        session = link.session
        target = link.keys.get(key, key)
        # Every reply, not one per key (`_ALL`): two daemons with one id must both be seen.
        # No `bus_errors` wrapper here: a generator context manager per query costs more
        # than the rest of this function (BENCHMARKS.md, section 1).
        try:
            if payload is None:
                handler = session.get(target, timeout=timeout or link.timeout, consolidation=_ALL)
            else:
                link.confirming()  # the machine asks this Rider about what it sends
                link.ledger.sent(payload)  # before it goes: the machine may ask at once
                handler = session.get(
                    target,
                    payload=payload,
                    encoding=MSGPACK,
                    attachment=link.attachment,
                    timeout=timeout or link.timeout,
                    consolidation=_ALL,
                )
            replies = list(handler)
        except zenoh.ZError as exc:
            raise bus_error(f"cannot query {key}", exc) from exc
        return self.pins.check_repliers(key, replies)
