"""The supervisor's side of Zenoh: the machine's router, and its voice while the daemon is down.

The supervisor's session runs in router mode on the machine's public endpoints; the daemon
child connects to it as a client over a private socket, and Riders connect to the router. So
Riders stay connected across a daemon restart, and hear the supervisor in between: a FAULT_HW
status on `machine/<id>/status`, answers to status queries, and a clear NOT_AVAILABLE error
for commands. The daemon's liveliness token tells the supervisor the child is up or gone.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh
from pydantic import BaseModel

from ride_machine.common.zenoh_session import file_config
from ride_machine.hal.base import HalError
from ride_machine.schema import keys as machine_keys
from ride_machine.schema.codec import DecodeError, Format, decode, encode
from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.status import Fault, FaultCode, MachineState, Status
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.errors import Busy, MachineError, NotAvailable
from ride_machine.service.threads import NamedThread

from .commands import command_route
from .injection import Injection, SimPort
from .publications import faulted
from .reads import latest, matching
from .request import Request
from .routes import Route, declare
from .session import zenoh_config

log = logging.getLogger(__name__)


ZENOH_LEASE_MS = 10_000
"""Zenoh's own lease where a config sets none."""


def router_config(
    path: Path | None, listen: list[str], connect: list[str], private: str, hang_s: float = 0.0
) -> zenoh.Config:
    """The daemon's own session config, as a router that also listens on `private`; its lease
    at least `hang_s` (`lease_at_least`)."""
    conf = zenoh_config(path, listen, connect)
    endpoints = json.loads(conf.get_json("listen/endpoints") or "[]")
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([*endpoints, private]))
    lease_at_least(conf, hang_s)
    return conf


def child_config(path: Path | None, private: str, hang_s: float = 0.0) -> str:
    """The daemon child's Zenoh config (JSON): a client of the supervisor's private endpoint,
    its lease at least `hang_s` (`lease_at_least`).

    A client listens nowhere, so nobody reaches the daemon but through the router, where the
    access control is enforced; the child itself runs none (it would deny its only link).
    """
    conf = file_config(path)
    lease_at_least(conf, hang_s)
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([private]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("access_control/enabled", "false")
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", "null")
    conf.insert_json5("scouting/multicast/enabled", "false")
    return str(conf)


def lease_at_least(conf: zenoh.Config, hang_s: float) -> None:
    """A lease of at least `hang_s`, the supervisor's own limit for a frozen daemon (`--hang`).

    Each end of a link drops it after the other end's lease without a word from it, so the
    router and the child both need it: with the shipped profiles' 1 s lease, a daemon that
    `--hang 3` lets wake up from a 1.5 s freeze left the bus all the same (the router dropped
    it, or it dropped the router's link as it woke), and its token's going killed it. A longer
    lease only slows how fast a Rider notices the supervisor itself gone, and only where
    `--hang` is longer than the lease."""
    lease_ms = json.loads(conf.get_json("transport/link/tx/lease") or str(ZENOH_LEASE_MS))
    conf.insert_json5("transport/link/tx/lease", json.dumps(max(lease_ms, round(hang_s * 1e3))))


def requires_credentials(conf: zenoh.Config) -> bool:
    """True when the router checks user/password (so the child must present some)."""
    return json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file") or "null") is not None


class SupervisorBus:
    """Watches the daemon child's presence and speaks for the machine while it is down."""

    def __init__(
        self,
        session: zenoh.Session,
        config: MachineConfig,
        *,
        world: SimPort | None = None,
        on_presence: Callable[[bool], None],
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.session = session
        self.config = config
        self.world = world
        self._plant = PlantRequests()
        self.on_presence = on_presence
        self.wall = wall
        self.base = config.key_base
        self._lock = threading.Lock()
        self._last: tuple[bytes, str] | None = None
        self._down: Status | None = None
        self._down_entities: list[Any] = []
        self._notice: Completion | None = None
        """The notice of the motion the daemon left when it died (answered while down)."""
        self._notified: str | None = None
        self._declared: list[Any] = []

    def start(self) -> None:
        s, b = self.session, self.base
        self._status_pub = s.declare_publisher(
            f"{b}/status",
            encoding=Format.MSGPACK.value,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_HIGH,
            express=True,
            # Our own FAULT_HW must not come back to us as "the daemon's last status".
            allowed_destination=zenoh.Locality.REMOTE,
        )
        self._declared.append(self._status_pub)
        self._declared.append(s.declare_subscriber(f"{b}/status", self._on_daemon_status))
        self._declared.append(
            s.liveliness().declare_subscriber(f"{b}/alive", self._on_token, history=True)
        )
        # Always: the daemon child leaves sim/** to its supervisor (one answer, never two).
        # The plant answers over a socket: on a thread of its own, never Zenoh's.
        sim = Injection(b, self.world, self.config.hal.backend, self._plant.run, self.wall)
        self._declared += declare(s, b, self, sim.routes())
        # Riders accept answers for this machine from its holder and from this session only.
        self._declared.append(
            s.liveliness().declare_token(machine_keys.supervisor_key(b, str(s.zid())))
        )
        log.info("event=supervisor_bus_started base=%s zid=%s", b, s.zid())

    def _source(self, sn: int) -> zenoh.SourceInfo:
        return zenoh.SourceInfo(self._status_pub.id, sn)

    def close(self) -> None:
        self._plant.close()
        with self._lock:
            entities, self._down_entities = self._down_entities, []
        for entity in reversed(self._declared + entities):
            entity.undeclare()
        self._declared.clear()

    # ------------------------------------------------------------------------ daemon down
    def daemon_down(self, reason: str) -> Status:
        """Publish FAULT_HW (DAEMON_DIED); answer status and command queries until `daemon_up`.

        A motion the daemon had under way (its last `Status.motion`) has ended with it: the
        supervisor sends that transaction's one completion notice (FAULT_HW, DAEMON_DIED)."""
        last = self._last_status()
        status = self._fault_status(reason)
        notice = self._abandoned(last, status, reason)
        with self._lock:
            self._down = status
            first = not self._down_entities
            if notice is not None:
                self._notice = notice
        if first:
            entities = declare(self.session, self.base, self, self._down_routes())
            with self._lock:
                self._down_entities = entities
        self._status_pub.put(encode(status), source_info=self._source(status.seq))
        if notice is not None:
            self.session.put(
                f"{self.base}/done/{notice.transaction_id}",
                encode(notice),
                encoding=Format.MSGPACK.value,
                allowed_destination=zenoh.Locality.REMOTE,
                source_info=self._source(status.seq),
            )
        return status

    def _abandoned(self, last: Status | None, down: Status, reason: str) -> Completion | None:
        motion = last.motion if last is not None else None
        with self._lock:
            if motion is None or motion.transaction_id == self._notified:
                return None
            self._notified = motion.transaction_id
        return Completion(
            machine_id=self.config.machine.id,
            transaction_id=motion.transaction_id,
            command=motion.command,
            outcome=Outcome.FAULT_HW,
            code=FaultCode.DAEMON_DIED.value,
            reason=f"{reason}; the machine daemon died during {motion.command}",
            state=down.state,
            started_at=motion.started_at,
            time=down.time,
        )

    def _down_routes(self) -> list[Route]:
        """What the supervisor answers while the daemon is down."""
        return [
            Route("status", latest(f"{self.base}/status", lambda: self._down)),
            command_route(self._refuse_command),
            Route("done/**", self._on_done),
        ]

    def state(self) -> MachineState | None:
        """`Host`: the state a refusal states (FAULT_HW while the daemon is down)."""
        with self._lock:
            down = self._down
        return down.state if down is not None else None

    def _on_done(self, request: Request) -> None:
        """While the daemon is down: the notice of the motion it left (others: no answer)."""
        with self._lock:
            notice = self._notice
        found = [] if notice is None else [(f"done/{notice.transaction_id}", notice)]
        matching(request, self.base, found)

    def _refuse_command(self, request: Request) -> None:
        raise NotAvailable(
            "the machine daemon is down and being restarted by its supervisor; outputs are"
            " safe; retry when machine/<id>/alive is back"
        )

    def republish(self) -> None:
        """The heartbeat while the daemon is down (late joiners and lossy links)."""
        with self._lock:
            down = self._down
            if down is None:
                return
            down = down.model_copy(update={"seq": down.seq + 1, "time": self.wall()})
            self._down = down
        self._status_pub.put(encode(down), source_info=self._source(down.seq))

    def daemon_up(self) -> None:
        """The daemon answers for itself again."""
        with self._lock:
            self._down = None
            entities, self._down_entities = self._down_entities, []
        for entity in entities:
            entity.undeclare()

    def _fault_status(self, reason: str) -> Status:
        fault = Fault(code=FaultCode.DAEMON_DIED, message=f"{reason}; outputs forced safe")
        now = self.wall()
        last = self._last_status()
        if last is None:
            return Status(
                machine_id=self.config.machine.id,
                state=MachineState.FAULT_HW,
                fault=fault,
                seq=0,
                cycle=0,
                time=now,
                heartbeat_s=self.config.bus.heartbeat_s,
            )
        # `republish()` keeps this heartbeat period.
        period = self.config.bus.heartbeat_s
        return faulted(
            last, fault, now, session=None, motion=None, uptime_s=0.0, heartbeat_s=period
        )

    def _last_status(self) -> Status | None:
        with self._lock:
            last = self._last
        if last is None:
            return None
        data, encoding = last
        fmt = Format.JSON if encoding.startswith(Format.JSON) else Format.MSGPACK
        try:
            return decode(Status, data, fmt)
        except DecodeError as exc:
            log.warning("event=daemon_status_undecodable error=%r", exc.error.message)
            return None

    # -------------------------------------------------------------------------- callbacks
    def _on_daemon_status(self, sample: zenoh.Sample) -> None:
        # Decoded only when needed: the daemon may publish at every cycle while moving.
        with self._lock:
            self._last = (sample.payload.to_bytes(), str(sample.encoding))

    def _on_token(self, sample: zenoh.Sample) -> None:
        self.on_presence(sample.kind == zenoh.SampleKind.PUT)


class PlantRequests:
    """`sim/**` work done on a thread of its own, in arrival order: the simulated plant is
    another process and each request a round trip to it, which a Zenoh callback must not wait
    for. A plant that does not answer makes the request `NOT_AVAILABLE`."""

    PENDING_MAX = 256
    """Requests waiting at most: a flood of `sim/world` is refused BUSY, not queued without end."""

    def __init__(self) -> None:
        self._queue: queue.Queue[tuple[Request, Callable[[], BaseModel]] | None] = queue.Queue(
            self.PENDING_MAX
        )
        self._thread = NamedThread(target=self._serve, name="sim-requests", daemon=True)
        self._thread.start()

    def run(self, request: Request, make: Callable[[], BaseModel]) -> None:
        """`Runner`: `make` and the reply to `request` on this thread, after what waits."""
        try:
            self._queue.put_nowait((request, make))
        except queue.Full:
            raise Busy(f"{self.PENDING_MAX} simulator requests are waiting; retry later") from None

    def _serve(self) -> None:
        while (item := self._queue.get()) is not None:
            request, make = item
            try:
                request.reply(make())
            except MachineError as exc:
                request.refuse(exc)
            except HalError as exc:  # the plant is gone or did not answer in time
                request.refuse(NotAvailable(f"the simulated plant: {exc}"))

    def close(self) -> None:
        with contextlib.suppress(queue.Full):  # after what waits: each still gets its answer
            self._queue.put(None, timeout=2.0)
        self._thread.join(timeout=2.0)
