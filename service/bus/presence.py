"""Who else is on the bus: other holders of this machine's id, and the Riders' presence and
heartbeats. Callbacks only record what they saw; the scan loop judges it."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from schema import rider as rider_keys
from schema.events import RiderEvent
from service.bus.callbacks import direct
from service.config.model import MachineConfig
from service.core.loop import LoopCall, ScanLoop

log = logging.getLogger(__name__)

MAX_RIDERS = 1024
"""Riders whose heartbeat the bus keeps track of at once."""
ID_PROBE_S = 1.0
"""Bound of the start-up liveliness query for this machine's id. It returns as soon as every
connected peer has answered (no wait at all for a lone daemon); the bound only matters on a
slow link."""


def holders_of(session: zenoh.Session, base: str, timeout: float = ID_PROBE_S) -> list[str]:
    """The other sessions that hold `base` now (`?` for one that holds `alive` but names no
    holder: an older daemon). Asked before this daemon declares its own tokens."""
    own = str(session.zid())
    found: set[str] = set()
    alive = False
    for reply in session.liveliness().get(f"{base}/**", timeout=timeout):
        if reply.ok is None:
            continue
        rest = str(reply.ok.key_expr)[len(base) + 1 :]
        if rest == "alive":
            alive = True
        elif rest.startswith("holder/"):
            found.add(rest[len("holder/") :])
    found.discard(own)
    if alive and not found:
        found.add("?")
    return sorted(found)


@dataclass
class Presence:
    """Duplicates of this machine's id, and the Riders alive; `RiderBeats` for the loop."""

    session: zenoh.Session
    loop: ScanLoop
    config: MachineConfig
    clock: Callable[[], float]
    others: set[str] = field(default_factory=set)
    """Other sessions that hold this machine's id (its `holder/<zid>` token): duplicates."""
    riders_alive: set[str] = field(default_factory=set)
    _beats: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.base = self.config.key_base
        self.zid = str(self.session.zid())

    def declare(self) -> list[Any]:
        """The subscribers; the caller undeclares them."""
        s, live = self.session, self.session.liveliness()
        # Each callback only notes what arrived (a set, a dict, the inbox): run on Zenoh's own
        # thread, without a Python thread each, and in arrival order.
        rider, beat, holder = (
            direct(fn) for fn in (self._on_rider, self._on_heartbeat, self._on_holder)
        )
        return [
            live.declare_subscriber(rider_keys.ALIVE_KEYS, rider, history=True),
            s.declare_subscriber(rider_keys.HEARTBEAT_KEYS, beat),
            # Before our own token: any other holder of this id is a duplicate, now or later.
            live.declare_subscriber(f"{self.base}/holder/*", holder, history=True),
        ]

    def _on_holder(self, sample: zenoh.Sample) -> None:
        """Another session declared (or dropped) this machine's id: both stop and refuse
        motion until one of them is alone again; each judges for itself, so both do."""
        zid = str(sample.key_expr).rsplit("/", 1)[-1]
        if zid == self.zid:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.others.add(zid)
            log.error("event=duplicate_id id=%s other_session=%s", self.config.machine.id, zid)
        else:
            self.others.discard(zid)
            log.warning("event=duplicate_gone id=%s other_session=%s", self.config.machine.id, zid)
        others = tuple(sorted(self.others))

        def update(loop: ScanLoop, now: float) -> None:
            loop.control.duplicate_id(others, self.zid, now)

        self.loop.inbox.put(LoopCall(update))

    def _on_heartbeat(self, sample: zenoh.Sample) -> None:
        """Only the arrival time is kept (one dict write): the scan loop judges it."""
        rider = rider_keys.rider_of(str(sample.key_expr))
        # Bounded: a flood of made-up Rider ids cannot grow this without end.
        if rider is not None and (rider in self._beats or len(self._beats) < MAX_RIDERS):
            self._beats[rider] = self.clock()

    def last_heartbeat(self, rider: str) -> float | None:
        """`RiderBeats` for the scan loop: when `rider`'s heartbeat last arrived."""
        return self._beats.get(rider)

    def _on_rider(self, sample: zenoh.Sample) -> None:
        rider = rider_keys.rider_of(str(sample.key_expr))
        if rider is None:
            return  # rider/<login>/<zid>/alive: anything else is not a Rider's token
        alive = sample.kind == zenoh.SampleKind.PUT
        if alive:
            self.riders_alive.add(rider)
        else:
            self.riders_alive.discard(rider)
            self._beats.pop(rider, None)

        def update(loop: ScanLoop, now: float) -> None:
            control = loop.control
            if control.controller_rider != rider:
                return
            policy = self.config.rider_loss.policy
            acted = False
            if alive:
                control.rider_back()
            elif acted := control.rider_lost(now):
                log.warning("event=rider_lost rider=%s policy=%s", rider, policy)
            # Through the recorder: after what it holds (the events of commands answered
            # since the last cycle), before the state change this causes.
            kind = "rider_returned" if alive else "rider_lost"
            # Left at rest (the end of `rider start --wait`) or lost while its motion runs.
            mid_motion = acted or control.is_moving()
            event = RiderEvent(
                kind=kind, rider=rider, policy=str(policy), acted=acted, mid_motion=mid_motion
            )
            loop.recorder.emit(event, now)

        self.loop.inbox.put(LoopCall(update))
