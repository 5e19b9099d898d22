"""The Rider deadman: the controlling Rider (the sender of the last moving command) as the
machine sees it, judged on its liveliness token and its heartbeats, and what its loss does:
`rider_loss.policy`, through the table's `Event.RIDER_LOST` row (pause → PAUSED, stop → DONE).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

from schema.status import MOTION_STATES, MachineState
from service.config.model import RiderLossPolicy
from service.core.statemachine.table import Event

if TYPE_CHECKING:
    from service.core.statemachine.machine import StateMachine


class Verdict(Enum):
    """What a heartbeat check found."""

    QUIET = "nothing changed"
    LOST = "silent past the timeout: lost"
    BACK = "a heartbeat after a loss: back"


@dataclass(slots=True)
class RiderWatch:
    """The controlling Rider; a fresh one for each moving command."""

    id: str | None = None
    connected: bool = False
    gone_at: float | None = None
    """When its token went (the grace period runs from here); None: not gone."""
    heard_at: float = 0.0
    """Its last sign of life: the command itself, then each heartbeat."""
    warning: str | None = None

    def gone(self, now: float, grace_s: float) -> bool:
        """Its token went: True if the rider-loss policy applies now (no grace period)."""
        self.connected = False
        if grace_s > 0:
            self.gone_at = now
            return False
        return True

    def back(self) -> None:
        self.connected = True
        self.gone_at = None

    def grace_over(self, now: float, grace_s: float) -> bool:
        """Its token went and did not come back within the grace period."""
        gone = self.gone_at
        return gone is not None and now - gone >= grace_s

    def heard(self, at: float | None, now: float, timeout_s: float) -> Verdict:
        """A heartbeat last arrived at `at` (None: never): LOST once silent past `timeout_s`;
        BACK when one arrives after a loss (nothing moves by itself)."""
        verdict = Verdict.QUIET
        if at is not None and at > self.heard_at:
            self.heard_at = at
            if not self.connected:
                self.back()
                verdict = Verdict.BACK
        if self.connected and now - self.heard_at > timeout_s:
            return Verdict.LOST
        return verdict


def lost(m: StateMachine, now: float) -> bool:
    """The controlling Rider is gone: apply the rider-loss policy now, or after the
    configured grace period if it does not come back; True if it acted now."""
    if m.watch.gone(now, m.config.rider_loss.grace_s):
        return apply_loss(m, now)
    return False


def heard(m: StateMachine, at: float | None, now: float) -> Verdict:
    """`at`: when the controlling Rider's heartbeat last arrived (None: never). Silent for
    `rider_loss.timeout_s` → LOST (the policy applies); a heartbeat after a loss → BACK (a
    paused ride stays paused)."""
    if m.watch.id is None:
        return Verdict.QUIET
    verdict = m.watch.heard(at, now, m.config.rider_loss.timeout_s)
    if verdict is Verdict.LOST:
        lost(m, now)
    return verdict


def apply_loss(m: StateMachine, now: float) -> bool:
    """The policy, now: True if it paused or stopped a motion."""
    m.watch.gone_at = None
    policy = m.config.rider_loss.policy
    if m.state not in MOTION_STATES or policy is RiderLossPolicy.IGNORE:
        return False
    m.watch.warning = f"controlling Rider lost during {m.state}; policy {policy}"
    if m.target(Event.RIDER_LOST) is MachineState.PAUSED:
        m.pause(now, "Rider lost", Event.RIDER_LOST)
    else:
        m.stop(now, "Rider lost", "RIDER_LOST", Event.RIDER_LOST)
    return True


MAX_RIDERS = 1024
"""Riders whose heartbeat is kept track of at once."""


class Heartbeats:
    """The Riders' heartbeats as data: written from the bus's callback (one dict write per
    heartbeat, `LoopPort.heartbeat`), read by the scan loop's deadman."""

    def __init__(self, limit: int = MAX_RIDERS) -> None:
        self.limit = limit
        self._at: dict[str, float] = {}
        self._gone: dict[str, None] = {}
        """Riders whose token went (oldest first): a heartbeat of theirs that arrives after
        it is one the token's going overtook, not a sign of life."""

    def beat(self, rider: str, at: float) -> None:
        """`rider`'s heartbeat arrived at `at`; a flood of made-up ids cannot grow this
        without end. One from a Rider whose token has gone is ignored: a heartbeat sent just
        before it closed can arrive after its token's going (another priority, another
        queue) and made the deadman take it back, then lose it a second time (run 21)."""
        if rider in self._gone:
            return
        if rider in self._at or len(self._at) < self.limit:
            self._at[rider] = at

    def forget(self, rider: str) -> None:
        """Its token went: its heartbeats are history until the token is back."""
        self._at.pop(rider, None)
        self._gone[rider] = None
        if len(self._gone) > self.limit:
            del self._gone[next(iter(self._gone))]

    def returned(self, rider: str) -> None:
        """Its token is back (a link that came back): its heartbeats count again."""
        self._gone.pop(rider, None)

    def last_heartbeat(self, rider: str) -> float | None:
        return self._at.get(rider)
