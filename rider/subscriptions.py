"""Following a machine's publications: subscribers under its keys that drop what another session
publishes there, `subscribe` (callbacks on Zenoh's thread) and `watch` (an iterator)."""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import zenoh

from ride_machine.schema.status import Status

from .errors import BadReply, BusError
from .link import Link, bus_errors, direct
from .machines import Machines
from .pinning import Pinning
from .replies import Update, decode_update

log = logging.getLogger("rider.client")  # one logger for the whole client, as before its split

FOREIGN_LOG_EVERY_S = 10.0
"""A `foreign_sample` warning at most this often (the first at once)."""


class Subscription:
    """What `Rider.subscribe` declared; `close()` undeclares it all (also as a context manager)."""

    def __init__(self, entities: list[Any]) -> None:
        self._entities = entities

    def close(self) -> None:
        """Undeclare everything; never raises, so a broken session can still be cleaned up."""
        entities, self._entities = self._entities, []
        for entity in reversed(entities):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Throttle:
    """A line that may repeat at any rate: the first passes, then at most one per `every_s`,
    saying how many were held back since the last (thread-safe: Zenoh's threads call it)."""

    def __init__(self, every_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s = every_s
        self.clock = clock
        self._lock = threading.Lock()
        self._next = -math.inf
        self._held = 0

    def allow(self) -> int | None:
        """None: hold this one back (counted); else how many were held back before it."""
        with self._lock:
            now = self.clock()
            if now < self._next:
                self._held += 1
                return None
            held, self._held = self._held, 0
            self._next = now + self.every_s
            return held


class Subscriptions:
    """Subscribers under this Rider's machine, guarded by its pinning."""

    def __init__(self, link: Link, machines: Machines, pins: Pinning) -> None:
        self.link = link
        self.machines = machines
        self.pins = pins
        self._foreign = Throttle(FOREIGN_LOG_EVERY_S)
        """The `foreign_sample` warning: a peer can publish under the machine's keys at any
        rate, and a line per sample cost the Rider's thread more than the sample did."""

    def subscribe(
        self,
        keys: Iterable[str],
        on_update: Callable[[Update], None],
        on_presence: Callable[[bool], None] | None,
    ) -> Subscription:
        """Decoded publications to `on_update`, the machine's presence to `on_presence`, on
        Zenoh's thread (`Rider.subscribe`)."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                update = decode_update(sample)
            except BadReply as exc:
                log.warning("event=bad_sample key=%s error=%r", sample.key_expr, str(exc))
                return
            if update is not None:
                on_update(update)

        def on_token(sample: zenoh.Sample) -> None:
            if on_presence is not None:
                on_presence(sample.kind == zenoh.SampleKind.PUT)

        return self.declare(keys, on_sample, on_token if on_presence is not None else None)

    def watch(
        self,
        keys: Iterable[str],
        current: Callable[[], Status],
        *,
        timeout: float | None = None,
        capacity: int = 4096,
    ) -> Iterator[Update]:
        """Updates on `keys` as published, starting with `current()` when `status` is one of
        them; stops after `timeout` seconds without any update (None = never)."""
        q: queue.Queue[zenoh.Sample] = queue.Queue(maxsize=capacity)

        def on_sample(sample: zenoh.Sample) -> None:
            # A slow reader drops updates rather than stall Zenoh's thread.
            with contextlib.suppress(queue.Full):
                q.put_nowait(sample)

        with self.declare(keys, on_sample):
            if any(k == "status" for k in keys):
                yield current()
            while True:
                try:
                    sample = q.get(timeout=timeout)
                except queue.Empty:
                    return
                try:
                    update = decode_update(sample)
                except BadReply:
                    continue
                if update is not None:
                    yield update

    def declare(
        self,
        keys: Iterable[str],
        on_sample: Callable[[zenoh.Sample], None],
        on_token: Callable[[zenoh.Sample], None] | None = None,
    ) -> Subscription:
        """Subscribers on `keys` under this machine (and on its `alive` token, with history);
        all or nothing."""
        base, session = self.machines.base, self.link.session
        entities: list[Any] = []
        known = self.pins.holders(self.machines.pick())

        def on_member(sample: zenoh.Sample) -> None:
            kind, _, zid = str(sample.key_expr)[len(base) + 1 :].partition("/")
            known.update(kind, zid, sample.kind == zenoh.SampleKind.PUT)

        def guarded(sample: zenoh.Sample) -> None:
            if self.pins.sample_ok(sample):
                on_sample(sample)
            else:
                self._foreign_sample(sample)

        try:
            with bus_errors(f"cannot subscribe under {base}"):
                for kind in ("holder", "supervisor"):
                    entities.append(
                        session.liveliness().declare_subscriber(
                            f"{base}/{kind}/*", direct(on_member), history=True
                        )
                    )
                for key in keys:
                    entities.append(session.declare_subscriber(f"{base}/{key}", direct(guarded)))
                if on_token is not None:
                    entities.append(
                        session.liveliness().declare_subscriber(
                            f"{base}/alive", direct(on_token), history=True
                        )
                    )
        except BusError:
            Subscription(entities).close()
            raise
        return Subscription(entities)

    def _foreign_sample(self, sample: zenoh.Sample) -> None:
        suppressed = self._foreign.allow()
        if suppressed is not None:
            source = sample.source_info
            log.warning(
                "event=foreign_sample key=%s source=%s suppressed=%d",
                sample.key_expr,
                "none" if source is None else str(source.source_id.zid),
                suppressed,
            )
