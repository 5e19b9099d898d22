"""A machine's event history through the Rider: its pages (of one machine, or of every machine
that answers `*`), a summary per machine, and the history followed live without a gap."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import zenoh

from ride_machine.common.event_summary import EventSummary, summarize
from ride_machine.schema.codec import MAX_REPLY_BYTES
from ride_machine.schema.events import Event, EventPage, EventQuery

from .errors import BadReply, RiderError
from .link import Link
from .machines import Machines
from .replies import decode_reply, decode_sample
from .subscriptions import Subscriptions
from .transport import EMPTY_RETRY_S, Transport

log = logging.getLogger("rider.client")  # one logger for the whole client, as before its split


@dataclass(frozen=True)
class Back:
    """A machine's liveliness token (re)appeared: what it wrote out of sight is to be read."""

    machine_id: str


@dataclass
class Events:
    """The event history of this Rider's machine (or of every machine, with the id `*`)."""

    link: Link
    machines: Machines
    transport: Transport
    subscriptions: Subscriptions

    def pages(self, query: EventQuery | None = None) -> list[EventPage]:
        """Every page of the history `query` selects (`Rider.event_pages`)."""
        return self._pages_from(self.machines.base, query or EventQuery())

    def events(self, query: EventQuery | None = None, **criteria: Any) -> list[Event]:
        """The events `query` (or `EventQuery(**criteria)`) selects (`Rider.events`)."""
        query = query or EventQuery(**criteria)
        found = [e for page in self.pages(query) for e in page.events]
        if "*" in self.machines.pick():
            found.sort(key=lambda e: (e.time, e.machine_id, e.seq))
        return found

    def summary(
        self, since_time: float | None = None, until_time: float | None = None
    ) -> list[EventSummary]:
        """Sessions, ride time, E-stops and faults by code over a time range, per machine."""
        q = EventQuery(since_time=since_time, until_time=until_time)
        by_machine: dict[str, list[Event]] = {}
        for page in self.pages(q):
            by_machine.setdefault(page.machine_id, []).extend(page.events)
        return [
            summarize(mid, evs, since_time, until_time) for mid, evs in sorted(by_machine.items())
        ]

    def follow(
        self, query: EventQuery | None = None, *, timeout: float | None = None
    ) -> Iterator[Event | None]:
        """The history `query` selects, then each new event as it is written; None after each
        quiet `timeout` (`Rider.follow_events`)."""
        query = query or EventQuery()
        q: queue.Queue[zenoh.Sample | Back] = queue.Queue(maxsize=65536)

        def on_sample(sample: zenoh.Sample) -> None:
            with contextlib.suppress(queue.Full):
                q.put_nowait(sample)

        def on_token(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:  # `<prefix>/<id>/alive`
                with contextlib.suppress(queue.Full):
                    q.put_nowait(Back(str(sample.key_expr).rsplit("/", 2)[-2]))

        with self.subscriptions.declare(("events/*",), on_sample, on_token):
            seen: dict[str, int] = {}  # the newest seq received per machine, of any kind
            for event in self.events(query):
                seen[event.machine_id] = event.seq
                yield event
            while True:
                try:
                    item = q.get(timeout=timeout)
                except queue.Empty:
                    yield None
                    continue
                if isinstance(item, Back):
                    yield from self._caught_up(item.machine_id, seen, query)
                else:
                    yield from self._arrived(item, seen, query)

    def _caught_up(self, machine_id: str, seen: dict[str, int], query: EventQuery) -> list[Event]:
        """A machine back in sight (restarted, or its link back): what it wrote meanwhile, from
        its history. A gap is otherwise seen only at the next live event, which may be long in
        coming (a restart's events all published before this Rider's link came back)."""
        newest = seen.get(machine_id)
        if newest is None:
            return []
        out = self._missed(machine_id, newest + 1, None, query)
        if out:
            seen[machine_id] = max(newest, *(e.seq for e in out))
        return out

    def _arrived(
        self, sample: zenoh.Sample, seen: dict[str, int], query: EventQuery
    ) -> list[Event]:
        """A published event that `query` selects, after those missed before it (none if it
        was heard already, or does not decode)."""
        try:
            event = decode_sample(sample, Event, MAX_REPLY_BYTES)
        except BadReply as exc:
            log.warning("event=bad_event key=%s error=%r", sample.key_expr, str(exc))
            return []
        newest = seen.get(event.machine_id)
        if newest is not None and event.seq <= newest:
            return []
        out: list[Event] = []
        if newest is not None and event.seq > newest + 1:
            out = self._missed(event.machine_id, newest + 1, event.seq - 1, query)
        seen[event.machine_id] = event.seq
        if query.matches(event):
            out.append(event)
        return out

    def _missed(
        self, machine_id: str, first: int, last: int | None, query: EventQuery
    ) -> list[Event]:
        """The events `query` selects among seq `first`..`last` (None: the newest) of one
        machine, read from its history; none (with a warning) if it cannot be read."""
        bounds = [b for b in (last, query.until) if b is not None]
        until = min(bounds) if bounds else None
        gap = dataclasses.replace(
            query,
            since=max(first, query.since or 0),
            until=until,
            limit=None,
            last=None,
        )
        try:
            pages = self._pages_from(f"{self.link.key_prefix}/{machine_id}", gap)
        except RiderError as exc:
            log.warning(
                "event=events_gap_unread machine=%s first=%d last=%s error=%r",
                machine_id,
                first,
                last,
                str(exc),
            )
            return []
        return [e for page in pages for e in page.events if e.machine_id == machine_id]

    def _pages_from(self, base: str, query: EventQuery) -> list[EventPage]:
        pages: list[EventPage] = []
        pending = [(base, query)]
        while pending:
            base, q = pending.pop(0)
            for page in self._query(base, q):
                pages.append(page)
                if page.more and page.next_since is not None:
                    nxt = dataclasses.replace(q, since=page.next_since)
                    pending.append((f"{self.link.key_prefix}/{page.machine_id}", nxt))
        return pages

    def _query(self, base: str, q: EventQuery) -> list[EventPage]:
        key = f"{base}/events"
        params = q.params()
        selector = f"{key}?{params}" if params else key
        if "*" not in base:
            return [self.transport.get_one(selector, None, EventPage, None)]
        deadline = time.monotonic() + self.link.timeout
        while True:
            replies = self.transport.get(selector, None, None)
            if replies or time.monotonic() > deadline - EMPTY_RETRY_S:
                return [decode_reply(r, EventPage) for r in replies]
            time.sleep(EMPTY_RETRY_S)
