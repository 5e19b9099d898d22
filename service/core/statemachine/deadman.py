"""The Rider deadman: the controlling Rider (the sender of the last moving command) as the
machine sees it, judged on its liveliness token and its heartbeats. The watch says what it
found; the state machine applies `rider_loss.policy` through the table's `Occurrence.RIDER_LOST`
row (pause → PAUSED, stop → DONE).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from enum import Enum

from ride_machine.schema.status import MOTION_STATES, MachineState
from ride_machine.service.config.model import RiderLossPolicy


class Verdict(Enum):
    """What a heartbeat check found."""

    QUIET = "nothing changed"
    LOST = "silent past the timeout: lost"
    BACK = "a heartbeat after a loss: back"


@dataclass(slots=True)
class RiderWatch:
    """The controlling Rider: each moving command's sender takes it over (`take`)."""

    id: str | None = None
    connected: bool = False
    gone_at: float | None = None
    """When its token went (the grace period runs from here); None: not gone."""
    heard_at: float = 0.0
    """Its last sign of life: the command itself, then each heartbeat."""
    warning: str | None = None

    def take(self, rider: str | None, now: float) -> None:
        """A moving command from `rider`: it controls now (the command is a sign of life)."""
        self.id, self.connected, self.heard_at = rider, rider is not None, now
        self.gone_at = self.warning = None

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
        BACK when one arrives after a loss (nothing moves by itself); QUIET without a Rider."""
        verdict = Verdict.QUIET
        if self.id is None:
            return verdict
        if at is not None and at > self.heard_at:
            self.heard_at = at
            if not self.connected:
                self.back()
                verdict = Verdict.BACK
        if self.connected and now - self.heard_at > timeout_s:
            return Verdict.LOST
        return verdict

    def loss(self, state: MachineState, policy: RiderLossPolicy) -> bool:
        """Its loss is judged now (the grace period, if any, is over): True if the policy
        acts on `state` (a motion), with the warning the status shows."""
        self.gone_at = None
        if state not in MOTION_STATES or policy is RiderLossPolicy.IGNORE:
            return False
        self.warning = f"controlling Rider lost during {state}; policy {policy}"
        return True


MAX_RIDERS = 1024
"""Riders whose heartbeat is kept track of at once."""

SILENT_S = 120.0
"""A Rider silent this long is dropped from the table: longer than any `rider_loss.timeout_s`
plus `grace_s` (60 s each at most), after which its last heartbeat decides nothing."""


class Heartbeats:
    """The Riders' heartbeats as data: written from the bus's callbacks (`LoopPort.heartbeat`),
    read by the scan loop's deadman. Bounded: a newcomer first drops the Riders silent past
    `silent_s`, and a full table the one silent longest, never the one that controls the
    machine: made-up ids (a station's login lets it put any `<zid>` under it) cannot keep a
    real Rider's heartbeat out."""

    def __init__(self, limit: int = MAX_RIDERS, silent_s: float = SILENT_S) -> None:
        self.limit = limit
        self.silent_s = silent_s
        self.controller: str | None = None
        """The Rider that controls the machine (set by the deadman each cycle): never dropped."""
        self._at: OrderedDict[str, float] = OrderedDict()
        """Last heartbeat by Rider, the one silent longest first (a read never misses a Rider
        being moved to the end, as it could between a dict's pop and its insert)."""
        self._gone: dict[str, None] = {}
        """Riders whose token went (oldest first): a heartbeat of theirs that arrives after
        it is one the token's going overtook, not a sign of life."""
        self._lock = threading.Lock()
        """Held by the writers (Zenoh's callbacks, on one thread or more); the deadman reads
        without it."""

    def beat(self, rider: str, at: float) -> None:
        """`rider`'s heartbeat arrived at `at`. One from a Rider whose token has gone is
        ignored: a heartbeat sent just before it closed can arrive after its token's going
        (another priority, another queue) and made the deadman take it back, then lose it a
        second time (run 21)."""
        with self._lock:
            if rider in self._gone:
                return
            at_ = self._at
            if rider in at_:
                at_[rider] = at
                at_.move_to_end(rider)
                return
            self._make_room(at)
            at_[rider] = at

    def _make_room(self, now: float) -> None:
        """Before a newcomer: drop the Riders silent past `silent_s`, and if the table is still
        full the one silent longest; never the controller. `_lock` held. Only the table's head
        is looked at (it runs from the one silent longest), not every Rider in it."""
        at_, keep = self._at, self.controller
        drop: list[str] = []
        for rider, t in at_.items():
            if rider == keep:
                continue
            if now - t <= self.silent_s:
                if len(at_) - len(drop) >= self.limit:
                    drop.append(rider)
                break
            drop.append(rider)
        for rider in drop:
            del at_[rider]

    def forget(self, rider: str) -> None:
        """Its token went: its heartbeats are history until the token is back."""
        with self._lock:
            self._at.pop(rider, None)
            self._gone[rider] = None
            if len(self._gone) > self.limit:
                del self._gone[next(iter(self._gone))]

    def returned(self, rider: str) -> None:
        """Its token is back (a link that came back): its heartbeats count again."""
        with self._lock:
            self._gone.pop(rider, None)

    def last_heartbeat(self, rider: str) -> float | None:
        return self._at.get(rider)
