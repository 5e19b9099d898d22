"""The bus as a table of routes: a key, its handler, and what a wildcard query on it means.

Every queryable of the daemon and of the supervisor is declared here, through `dispatch`: it
makes the `Request`, applies the one wildcard rule, runs the handler, and turns any
`MachineError` the handler raises into the one refusal shape (`Request.refuse`), and any other
exception into one `INTERNAL` refusal and one logged traceback: no query goes unanswered.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import Enum
from typing import Any

import zenoh

from ride_machine.schema.codec import MAX_PAYLOAD_BYTES, sniff_format
from ride_machine.service.errors import BadKey, Internal, MachineError

from .callbacks import direct
from .request import Host, Request, encoding_of, reply_format

log = logging.getLogger(__name__)

Handler = Callable[[Request], None]


class Wildcard(Enum):
    """What a query with a wildcard (`*`, `**`, `$*`) in its key gets on a route."""

    READ = "read"
    """Answered: a read changes nothing (the handler replies for every key it covers)."""
    REFUSE = "refuse"
    """Refused with BAD_KEY: the key acts, and a wildcard may reach every machine."""
    REFUSE_WRITES = "refuse_writes"
    """Read without a payload; refused with one (a write must name one key of one machine)."""
    REFUSE_NAMED = "refuse_named"
    """Refused when it names this key (`machine/*/diag/reset`); a broader read that only
    happens to cover it (`diag/**`) gets no answer from this route."""


@dataclass(frozen=True)
class Route:
    """One queryable: `key` under the machine's base (as declared), and how it answers."""

    key: str
    handler: Handler
    wildcard: Wildcard = Wildcard.READ
    sniff: bool = False
    """Reply in the payload's format (a write); a read ignores its payload."""
    what: str = ""
    """The refusal of a wildcard names it: `wildcards are not allowed in <what>`."""
    example: str = ""
    """... and shows one key to use instead: `e.g. <base>/<example>`."""
    noun: str = "key"
    refusal: type[BadKey] = BadKey
    """`WildcardCommand` on `cmd/**`: that refusal is a Zenoh error reply, as documented."""
    keys: tuple[str, ...] = ()
    """Exact keys under `key` (under the machine's base) declared to the session as key
    expressions: a query on one of them is matched against a declared resource instead of
    the wildcard, on the hot path of every command (BENCHMARKS.md, section 1)."""
    direct: bool = False
    """Run the handler on Zenoh's receive thread instead of a Python thread of its own (one
    fewer thread and hop; `callbacks.direct`): only for handlers that never block (replies
    from published records; `cmd/**`, which runs a command only when the loop's lock is free
    and otherwise hands it to a thread of its own)."""

    @property
    def acts(self) -> bool:
        """A key that acts (a command, a write): a put on it is a mistake worth telling."""
        return self.wildcard is not Wildcard.READ

    def refuse_wildcard(self, base: str, key: str) -> MachineError:
        """The one wildcard refusal."""
        return self.refusal(
            f"wildcards are not allowed in {self.what}: {key!r}; name one {self.noun} of one"
            f" machine, e.g. {base}/{self.example}"
        )


def dispatch(route: Route, base: str, host: Host, query: zenoh.Query) -> None:
    """Answer one query on `route`: exactly one reply, or a refusal, or (a covered read) none."""
    # One read of the selector for the key and its parameters: each read crosses into Zenoh.
    key, _, parameters = str(query.selector).partition("?")
    body = query.payload
    # Its length first: a payload larger than any request may be is never copied (a handler
    # that reads it refuses it, `Request.payload`; a read that ignores it answers).
    size = len(body) if body is not None else 0
    payload = body.to_bytes() if body is not None and 0 < size <= MAX_PAYLOAD_BYTES else b""
    encoding = encoding_of(query)
    # The payload's format is told once, for the reply's and for reading it (`Request.raw`).
    sent = sniff_format(payload, encoding) if route.sniff and payload else None
    fmt = reply_format(parameters, encoding, sent)
    request = Request(query, key, payload, encoding, fmt, host, sent=sent, size=size)
    try:
        rule = route.wildcard
        if rule is not Wildcard.READ and request.wild:
            if rule is Wildcard.REFUSE_NAMED and not key.endswith("/" + route.key):
                query.drop()
                return
            if rule is not Wildcard.REFUSE_WRITES or size:
                raise route.refuse_wildcard(base, key)
        route.handler(request)
    except MachineError as exc:
        request.refuse(exc)
    except Exception as exc:  # a handler's bug: its query still gets its one reply
        error = type(exc).__name__
        try:
            request.refuse(
                Internal(
                    f"internal error ({error}) answering {key}; the machine's log has its"
                    " traceback (event=handler_failed)"
                )
            )
            refused = True
        except zenoh.ZError:  # it had answered, and so ended, the query before it failed
            refused = False
        log.error(
            "event=handler_failed key=%s error=%s refused=%s", key, error, refused, exc_info=exc
        )


def declare(session: zenoh.Session, base: str, host: Host, routes: Iterable[Route]) -> list[Any]:
    """One queryable per route on `<base>/<route.key>` (and its exact `keys` declared as key
    expressions), and beside a route that acts a subscriber that tells a put on it in the log
    (`PutWarner`); the caller undeclares them."""

    def callback(route: Route) -> Callable[[zenoh.Query], None] | zenoh.handlers.Callback[Any]:
        def fn(query: zenoh.Query) -> None:
            dispatch(route, base, host, query)

        return direct(fn) if route.direct else fn

    declared: list[Any] = []
    warner = PutWarner()
    for r in routes:
        declared += [DeclaredKey(session, f"{base}/{k}") for k in r.keys]
        declared.append(session.declare_queryable(f"{base}/{r.key}", callback(r)))
        if r.acts:
            declared.append(session.declare_subscriber(f"{base}/{r.key}", direct(warner.sample)))
    return declared


PUT_LOG_S = 1.0
"""At most one line this often: the puts in between are counted in the next one. A peer that
puts as fast as it can (zenoh-python's z_pub_thr.py) costs a counter and a clock read a sample,
on Zenoh's thread, and the log a line a second."""


class PutWarner:
    """A put (or delete) on a key that acts does nothing: commands and writes are queries,
    the reply is the answer. Nobody can be answered on a put, so it is logged, naming the key
    and the query to send instead (a `zenoh put` or `z_put.py` where `zenoh get` was meant)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.seen = 0
        """Puts and deletes so far."""
        self._told = 0
        """`seen` when the last line was logged."""
        self._next = float("-inf")

    def sample(self, sample: zenoh.Sample) -> None:
        """On Zenoh's thread, for every sample: cheap until a line is due."""
        self.seen += 1
        now = self.clock()
        if now < self._next:
            return
        self._next = now + PUT_LOG_S
        unlogged, self._told = self.seen - self._told - 1, self.seen
        key = str(sample.key_expr)
        kind = "delete" if sample.kind == zenoh.SampleKind.DELETE else "put"
        log.warning(
            "event=put_ignored key=%r kind=%s unlogged=%d hint=%r",
            key,
            kind,
            unlogged,
            f"{key} answers queries, not puts: send a query (zenoh get -s '{key}' -v"
            " '<JSON>', z_get.py, the rider CLI); nothing was done",
        )


class DeclaredKey:
    """A key expression declared to a session, undeclared like the queryables beside it."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.session = session
        self.key_expr = session.declare_keyexpr(key)

    def undeclare(self) -> None:
        self.session.undeclare(self.key_expr)
