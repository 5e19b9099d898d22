"""Queries that change nothing: the latest records, diagnostics, completion notices, history,
and a config check. Answered on Zenoh's thread (or the event log's reader) without touching
machine state; a read may use wildcards."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

import zenoh
from pydantic import BaseModel

from ride_machine.schema.codec import Format
from ride_machine.schema.completion import Completion
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.events import EventPage, EventQuery, QueryError, selector_params
from ride_machine.schema.findings import Findings
from ride_machine.service.adapters.eventlog import EventLog
from ride_machine.service.core.scan.port import LoopPort
from ride_machine.service.errors import (
    BadKey,
    BadRequest,
    Busy,
    InProgress,
    NotAvailable,
    StorageFailed,
    UnknownTransaction,
)

from .request import Request, put
from .routes import Handler, Route


class ConfigChecker(Protocol):
    """Validates the running config, or a candidate one sent as a TOML/JSON payload."""

    def __call__(self, candidate: bytes | None) -> Findings: ...


def latest(key: str, get: Callable[[], BaseModel | None]) -> Handler:
    """A handler that answers with the latest record on `key` (none yet: no answer)."""

    def handler(request: Request) -> None:
        record = get()
        if record is None:
            request.query.drop()
        else:
            request.reply(record, key)

    return handler


def matching(request: Request, base: str, items: Iterable[tuple[str, BaseModel]]) -> None:
    """One reply per record whose key the (possibly wildcard) query selects."""
    query = request.query
    with query:
        for suffix, record in items:
            key = f"{base}/{suffix}"
            if query.key_expr.intersects(zenoh.KeyExpr(key)):
                put(query, key, record, request.fmt)


HISTORY_LOCK_TIMEOUT_S = 0.5
"""How long a history read waits for a cycle in progress (a stalled loop: read without it)."""


@dataclass
class Reads:
    """The daemon's read-only routes."""

    base: str
    port: LoopPort
    diag: Callable[[], CycleDiag]
    check_config: ConfigChecker | None = None
    events: EventLog | None = None

    def routes(self) -> list[Route]:
        b, port = self.base, self.port
        routes = [
            Route("status", latest(f"{b}/status", lambda: port.published().status), direct=True),
            Route("io/**", self.io, direct=True),
            Route("axis/**", self.axes, direct=True),
            Route("diag/cycle", self.cycle),  # sorts the stats window: not on Zenoh's thread
            Route("config/validate", self.validate),
            Route("done/**", self.done, direct=True),
            Route(
                "calibration",
                latest(f"{b}/calibration", lambda: port.published().calibration),
                direct=True,
            ),
        ]
        if self.events is not None:
            routes.append(Route("events", self.history))
        return routes

    def io(self, request: Request) -> None:
        points = self.port.published().io.values()
        matching(request, self.base, [(f"io/{p.kind}/{p.name}", p) for p in points])

    def axes(self, request: Request) -> None:
        records = self.port.published().axes.values()
        matching(request, self.base, [(f"axis/{r.axis}", r) for r in records])

    def cycle(self, request: Request) -> None:
        request.key = f"{self.base}/diag/cycle"
        if "reset" in request.query.parameters:
            # The old spelling of a reset: a write hidden in a parameter, which no ACL can see.
            raise BadKey(
                "diag/cycle is read-only; reset the counters with a query on"
                f" {self.base}/diag/reset"
            )
        request.reply(self.diag())

    def done(self, request: Request) -> None:
        """How a motion ended: its notice, IN_PROGRESS while it runs, or UNKNOWN_TRANSACTION;
        a wildcard (`done/**`) gets every notice the machine remembers."""
        if request.wild:
            notices = self.port.notices()
            matching(request, self.base, [(f"done/{n.transaction_id}", n) for n in notices])
            return
        key = request.key
        tid = key[len(f"{self.base}/done/") :]
        request.transaction_id = tid
        found = self.port.notice(tid)
        if isinstance(found, Completion):
            request.reply(found)
        elif found is not None:
            raise InProgress(
                f"{found.command} {tid} has not ended yet; its notice will be published on {key}"
            )
        else:
            raise UnknownTransaction(
                f"no motion {tid!r} is known here (never accepted, forgotten, or before this"
                " daemon started)",
                path="/transaction_id",
            )

    def validate(self, request: Request) -> None:
        request.key = f"{self.base}/config/validate"
        # Past MAX_PAYLOAD_BYTES `payload` refuses it: parsing runs on Zenoh's thread and holds
        # the GIL, and a few MiB would stall the scan loop.
        data = request.payload
        if data.lstrip()[:1] == b"{" and request.query.parameters.get("format") is None:
            request.fmt = Format.JSON  # a JSON candidate is answered in JSON (TOML keeps msgpack)
        if self.check_config is None:
            raise NotAvailable("no config checker")
        request.reply(self.check_config(data or None))

    def history(self, request: Request) -> None:
        """A page of the history (`?since=&until=&since_time=&until_time=&kind=&limit=&last=`),
        read on the event log's reader thread."""
        events = self.events
        assert events is not None
        request.key = f"{self.base}/events"
        if selector_params(str(request.query.parameters)).get("format", "").lower() == "json":
            request.fmt = Format.JSON  # `?last=5&format=json`: `&` separates here too
        try:
            q = EventQuery.from_text(str(request.query.parameters))
        except QueryError as exc:
            raise BadRequest(str(exc), path=f"?{exc.param}") from None

        def respond(page: EventPage) -> None:
            request.reply(page)

        def fail(message: str) -> None:
            request.refuse(StorageFailed(message))

        # The events of commands answered since the last cycle are written with the next one:
        # hand them over first, so the page has every command answered before it was asked.
        self.port.release_records(HISTORY_LOCK_TIMEOUT_S)
        if not events.read(q, respond, fail):
            raise Busy("event reader busy; retry later")
