"""Who asked, proven: the machine asks the Rider a request names whether it sent it.

A request names its Rider (`<login>/<zid>`) in its `rider` field (the ride's deadman) or its
attachment (who asked, for the history); the sender says so, and Zenoh does not tie a query to
the login that sent it. So before a motion command binds a ride to a Rider, or a write is
recorded as a Rider's, the daemon asks that Rider on `rider/<login>/<zid>/confirm` about the
request's digest (schema/rider.py). Under the ACL profiles only login `<login>` may declare that
queryable, so a "yes" proves the login; a station that copied another's Rider id gets a "no"
from the Rider it named, or no answer at all.

`ask` blocks for up to its timeout: never on Zenoh's own thread (the reply arrives there).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from enum import Enum

import zenoh

from ride_machine.schema.rider import confirm_key, digest, is_rider_id, operator_of
from ride_machine.service.core.commands.identity import Identity

log = logging.getLogger(__name__)

NOT_YET_S = 0.005
"""How long the machine waits before it asks again when no Rider answered at all."""


class Verdict(Enum):
    """What the named Rider said about a request."""

    CONFIRMED = "confirmed"
    """It sent it."""
    DENIED = "denied"
    """It answered, and did not send it (another sender used its id)."""
    SILENT = "silent"
    """No answer: no such Rider on the bus, a Rider without confirmations (another client, an
    older Rider), or one that did not answer within the timeout."""
    UNNAMED = "unnamed"
    """The id names no login (`<zid>` alone, a schema-1 Rider or the gateway's borrowed
    session): nobody to ask."""


@dataclass(frozen=True, slots=True)
class Answer:
    """A Rider's answer: the verdict, and the person it acted for when it names one."""

    verdict: Verdict
    operator: str | None = None

    def identity(self, rider: str) -> Identity | None:
        """Who asked, for the history: `rider` (and its person) once confirmed, else None."""
        return Identity(rider, self.operator) if self.verdict is Verdict.CONFIRMED else None


class Confirmer:
    """Asks Riders about requests on one session."""

    def __init__(self, session: zenoh.Session, timeout_s: float) -> None:
        self.session = session
        self.timeout_s = timeout_s

    def ask(self, rider: str, payload: bytes) -> Answer:
        """Whether Rider `rider` sent `payload` (the request's bytes as they came)."""
        if not is_rider_id(rider):
            return Answer(Verdict.UNNAMED)
        key, asked = confirm_key(rider), digest(payload)
        started = time.monotonic()
        deadline = started + self.timeout_s
        while True:
            try:
                replies = self.session.get(key, payload=asked, timeout=self.timeout_s)
                answers = [r.ok for r in replies if r.ok is not None]
            except zenoh.ZError as exc:  # a closing session
                log.warning("event=confirm_failed rider=%s error=%r", rider, str(exc))
                return Answer(Verdict.SILENT)
            # No answer before the timeout: no queryable was matched yet. A Rider's
            # declaration can reach the machine after its first request (Zenoh sends
            # declarations apart from queries): ask again until the timeout.
            if answers or time.monotonic() + NOT_YET_S >= deadline:
                break
            time.sleep(NOT_YET_S)
        verdict, operator = Verdict.SILENT, None
        if answers:
            said = [operator_of(a.payload.to_bytes()) for a in answers]
            confirmed = [name for yes, name in said if yes]
            verdict = Verdict.CONFIRMED if confirmed else Verdict.DENIED
            operator = next((name for name in confirmed if name), None)
        if verdict is not Verdict.CONFIRMED:
            log.warning(
                "event=rider_unconfirmed rider=%s verdict=%s waited_ms=%.1f",
                rider,
                verdict.value,
                (time.monotonic() - started) * 1000,
            )
        return Answer(verdict, operator)
