"""Who else is on the bus: other holders of this machine's id, and the Riders' presence and
heartbeats. Callbacks only hand the loop what they saw (through its port: a heartbeat, a task for
the scan thread); the scan loop judges it."""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field
from typing import Any

import zenoh

from ride_machine.schema import rider as rider_keys
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.port import LoopPort
from ride_machine.service.core.scan.tasks import Duplicates, RiderPresence

from .callbacks import direct

log = logging.getLogger(__name__)

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
    """Duplicates of this machine's id, and the Riders alive and beating."""

    session: zenoh.Session
    port: LoopPort
    config: MachineConfig
    others: set[str] = field(default_factory=set)
    """Other sessions that hold this machine's id (its `holder/<zid>` token): duplicates."""
    riders_alive: set[str] = field(default_factory=set)
    dropped: int = 0
    """Presence changes the scan loop's inbox had no room for (lost: logged, and counted)."""

    def __post_init__(self) -> None:
        self.base = self.config.key_base
        self.zid = str(self.session.zid())
        self._drops = itertools.count(1)  # its `next` is one step: callbacks on two threads

    def _hand_over(self, task: Duplicates | RiderPresence, what: str, *args: object) -> None:
        """Queue `task` for the scan thread. A full inbox drops it: counted, and said (`what`
        and its `args`, key=value) at the first drop and then at every power of two, so a
        storm of changes is not a storm of lines."""
        if self.port.submit(task):
            return
        n = self.dropped = next(self._drops)
        if n & (n - 1) == 0:
            log.warning(f"event=presence_dropped cause=inbox_full {what} dropped=%d", *args, n)

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
        self._hand_over(Duplicates(others, self.zid), "task=duplicates others=%s", ",".join(others))

    def _on_heartbeat(self, sample: zenoh.Sample) -> None:
        """Only the arrival time is kept (`Heartbeats.beat`): the scan loop judges it."""
        rider = rider_keys.rider_of(str(sample.key_expr))
        if rider is not None:
            self.port.heartbeat(rider)

    def _on_rider(self, sample: zenoh.Sample) -> None:
        rider = rider_keys.rider_of(str(sample.key_expr))
        if rider is None:
            return  # rider/<login>/<zid>/alive: anything else is not a Rider's token
        alive = sample.kind == zenoh.SampleKind.PUT
        if alive:
            self.riders_alive.add(rider)
            self.port.rider_back(rider)
        else:
            self.riders_alive.discard(rider)
            self.port.rider_gone(rider)
        self._hand_over(RiderPresence(rider, alive), "task=rider rider=%s alive=%s", rider, alive)
