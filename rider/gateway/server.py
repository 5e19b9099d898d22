"""The gateway assembled: the bus, the OPC UA server, the metrics endpoint, and the loop that
carries what the machines publish to both.

One asyncio loop owns the views and the address space. Zenoh's threads only hand samples to it
(`call_soon_threadsafe`); blocking Zenoh work (declarations, command round trips) runs on worker
threads. A publication the loop cannot keep up with is dropped and counted, never queued without
bound.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from asyncua import ua
from prometheus_client import (
    CollectorRegistry,
    GCCollector,
    PlatformCollector,
    ProcessCollector,
)

from ride_machine.rider.client import NoMachine, rider_login
from ride_machine.rider.gateway import nodeset_cache
from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.events import Event
from ride_machine.schema.status import Status

from .alarmlist import AlarmList
from .alarms import alarm_of
from .bus import Attached, Deliver, GatewayBus, Snapshot
from .exposition import serve
from .identity import (
    MANUFACTURER,
    PRODUCT_NAME,
    PRODUCT_URI,
    Limits,
    describe,
    diagnose,
    enable_diagnostics,
    version,
)
from .methods import Commander, bind_methods
from .metrics import GatewayStats, MachineCollector
from .model import MachineView
from .security import Rules, Users
from .space import NAMESPACE, Space
from .supervision import Supervisor, open_session_keys
from .uaserver import POLICIES, GatewayInternalServer, GatewayServer, open_sessions

log = logging.getLogger(__name__)

MAX_PENDING = 10_000
"""Publications waiting for the loop; beyond this they are dropped (and counted)."""
APPLICATION_URI = NAMESPACE
"""The gateway's OPC UA application URI: its certificate names it (`machine credentials init`)."""


@dataclass
class Options:
    """What `rider gateway` was told (rider/gateway/cli.py)."""

    connect: list[str]
    zenoh_config: Path | None
    opcua: tuple[str, int] = ("127.0.0.1", 4840)
    metrics: tuple[str, int] | None = ("127.0.0.1", 9464)
    read_only: bool = False
    users: dict[str, str] = field(default_factory=dict)
    operator_certs: dict[bytes, str] = field(default_factory=dict)
    certificate: Path | None = None
    private_key: Path | None = None
    session_timeout_s: float = 10.0
    forget_after_s: float = 30.0
    command_timeout_s: float = 2.0
    prefix: str = "machine"
    zenoh_threads: int = 1
    max_sessions: int = Limits.sessions
    cache_dirs: tuple[Path, ...] = ()
    """Where the standard address space's shelf may be kept, in order (none: in memory)."""


class Gateway:
    """Serves every machine the bus shows, until `stop` is set."""

    def __init__(self, options: Options) -> None:
        self.o = options
        self.views: dict[str, MachineView] = {}
        self.attached: dict[str, Attached] = {}
        self.dropped = 0
        self.ready = asyncio.Event()
        self._pending = 0
        self._inbox: asyncio.Queue[tuple[str, Any]] = asyncio.Queue()
        self._tasks: set[asyncio.Task[None]] = set()
        self._attaching: dict[str, bool] = {}
        """Machines being attached; True: its token came back meanwhile (read it again)."""
        self.iserver = GatewayInternalServer(
            Users(options.users, options.operator_certs), Limits(sessions=options.max_sessions)
        )
        self.server = GatewayServer(iserver=self.iserver)
        self.space = Space(self.server)
        self.alarms = AlarmList(self.iserver, self.iserver.calls)
        self.bus: GatewayBus | None = None
        self.supervisor = Supervisor(
            self._declare_rider,
            lambda: open_session_keys(self.server.iserver),
            options.session_timeout_s,
            login=rider_login(),
        )
        self.commander = Commander(self._send, self.supervisor.rider_for, options.read_only)
        self._version = version()[0]

    # ------------------------------------------------------------------------------- setup
    async def _opcua(self) -> None:
        o, s = self.o, self.server
        if o.cache_dirs:
            self.iserver.nodeset = await asyncio.to_thread(nodeset_cache.first, o.cache_dirs)
        await s.init()
        host, port = o.opcua
        s.set_endpoint(f"opc.tcp://{host}:{port}/")
        s.set_server_name(PRODUCT_NAME)
        s.product_uri, s.manufacturer_name = PRODUCT_URI, MANUFACTURER
        await s.set_application_uri(APPLICATION_URI)
        await describe(s, self.iserver.limits)
        await enable_diagnostics(s)
        policies = [ua.SecurityPolicyType.NoSecurity]
        tokens: list[type] = [ua.AnonymousIdentityToken]
        if o.certificate is not None and o.private_key is not None:
            await s.load_certificate(str(o.certificate))
            await s.load_private_key(str(o.private_key))
            policies += POLICIES
            # Without a certificate a password or a user certificate cannot be protected.
            tokens += [ua.UserNameIdentityToken, ua.X509IdentityToken]
        s.set_security_policy(policies, permission_ruleset=Rules())
        s.set_identity_tokens(tokens)
        # The longest a session may stay silent before it is closed (and its Riders end).
        timeout_ms = o.session_timeout_s * 1000
        s.iserver.max_session_timeout_ms = timeout_ms
        s.iserver.min_session_timeout_ms = min(1000.0, timeout_ms)
        await self.space.setup()
        self.alarms.idx = self.space.idx
        await s.start()

    def _metrics(self) -> Any:
        if self.o.metrics is None:
            return None
        registry = CollectorRegistry(auto_describe=False)
        registry.register(MachineCollector(lambda: list(self.views.values()), self.stats))
        # The gateway's own CPU, memory and Python runtime, as any exporter has them.
        ProcessCollector(registry=registry)
        PlatformCollector(registry=registry)
        GCCollector(registry=registry)
        host, port = self.o.metrics
        return serve(host, port, registry)

    def stats(self) -> GatewayStats:
        return GatewayStats(
            machines=sum(v.alive for v in self.views.values()),
            opcua_sessions=len(open_session_keys(self.server.iserver)),
            supervising=self.supervisor.supervising,
            updates_dropped=self.dropped,
            version=self._version,
        )

    # --------------------------------------------------------------------------------- run
    async def run(self, stop: asyncio.Event) -> None:
        o = self.o
        self.bus = await asyncio.to_thread(
            GatewayBus,
            o.connect,
            o.zenoh_config,
            prefix=o.prefix,
            timeout=o.command_timeout_s,
            zenoh_threads=o.zenoh_threads,
        )
        metrics: Any = None
        tasks: list[asyncio.Task[None]] = []
        try:
            await self._opcua()
            metrics = self._metrics()
            self.bus.follow(self._deliver())
            tasks = [
                asyncio.create_task(self._consume()),
                asyncio.create_task(self.supervisor.watch()),
                asyncio.create_task(self._forget()),
                asyncio.create_task(self._diagnostics()),
            ]
            self.ready.set()
            log.info(
                "event=gateway_ready opcua=%s:%s metrics=%s zenoh=%s mode=%s",
                *o.opcua,
                f"{o.metrics[0]}:{o.metrics[1]}" if o.metrics else "off",
                self.bus.zid,
                "monitor" if o.read_only else "operator",
            )
            await stop.wait()
        finally:
            await self._shutdown(tasks, metrics)

    async def _shutdown(self, tasks: list[asyncio.Task[None]], metrics: Any) -> None:
        for task in tasks:
            task.cancel()
        for task in tasks:
            try:
                await task
            except asyncio.CancelledError:
                pass
            except Exception:  # the session must still close (an open one hangs the exit)
                log.exception("event=task_failed task=%s", task.get_coro())
        await self.supervisor.close()
        with contextlib.suppress(Exception):  # a server that never started
            await self.server.stop()
        if metrics is not None:
            server, thread = metrics
            server.shutdown()
            thread.join(timeout=2.0)
        bus, self.bus = self.bus, None
        if bus is not None:
            for attached in self.attached.values():
                await asyncio.to_thread(attached.close)
            await asyncio.to_thread(bus.close)
        log.info("event=gateway_stopped")

    async def _diagnostics(self) -> None:
        """The server's diagnostics summary, every second."""
        iserver = self.iserver
        while True:
            sessions = len(open_sessions(iserver))
            subscriptions = len(iserver.subscription_service.subscriptions)
            await diagnose(self.server, iserver.counts, sessions, subscriptions)
            await asyncio.sleep(1.0)

    # ----------------------------------------------------------------------- machines
    def _arrive(self, machine_id: str, item: Any) -> None:
        """On the loop: queue what the bus delivered (presence is never dropped)."""
        if not isinstance(item, bool):
            if self._pending >= MAX_PENDING:
                self.dropped += 1
                return
            self._pending += 1
        self._inbox.put_nowait((machine_id, item))

    async def _consume(self) -> None:
        while True:
            machine_id, item = await self._inbox.get()
            try:
                await self._handle(machine_id, item)
            except Exception:  # one item that fails must not stop the gateway (it is logged)
                log.exception("event=update_failed machine=%s item=%s", machine_id, type(item))

    async def _handle(self, machine_id: str, item: Any) -> None:
        if isinstance(item, bool):
            await self._presence(machine_id, item)
            return
        self._pending -= 1
        view, node = self.views.get(machine_id), self.space.machines.get(machine_id)
        if view is None or node is None:
            return  # forgotten, or a sample that came before its token
        if isinstance(item, Event):
            view.count(item)
            if (alarm := alarm_of(item)) is not None:
                await node.fire(alarm, item.time)
        elif isinstance(item, Snapshot):
            view.apply(item.update, snapshot=True)
            await node.update(item.update, snapshot=True)
            await self._conditions(view, item.update)
        else:
            view.apply(item)
            await node.update(item)
            await self._conditions(view, item)

    async def _conditions(self, view: MachineView, update: Any) -> None:
        """A status the view took (not a late one) moves the machine's conditions."""
        if isinstance(update, Status) and view.status is update:
            await self.alarms.status(view.machine_id, update)

    async def _presence(self, machine_id: str, alive: bool) -> None:
        view = self.views.get(machine_id)
        if not alive:
            if view is not None and view.alive:
                view.presence(False, time.monotonic())
                if (node := self.space.machines.get(machine_id)) is not None:
                    await node.presence(False)
                await self.alarms.presence(machine_id, False, time.time())
                log.warning("event=machine_gone machine=%s", machine_id)
            return
        if view is None:
            view = self.views[machine_id] = MachineView(machine_id)
        view.presence(True, time.monotonic())
        node = self.space.machines.get(machine_id)
        if node is None:
            node = await self.space.add(machine_id)
            bind_methods(node.methods, machine_id, self.commander, self.iserver.calls)
        else:
            await node.presence(True)
        await self.alarms.presence(machine_id, True, time.time())
        attached = self.attached.get(machine_id)
        if attached is not None:
            self._background(self._refresh(attached))  # back from a drop-out
        elif machine_id in self._attaching:
            self._attaching[machine_id] = True  # back while attaching: read it again after
        elif self.bus is not None:
            self._attaching[machine_id] = False
            self._background(self._attach(self.bus, machine_id))
        log.info("event=machine_seen machine=%s", machine_id)

    async def _attach(self, bus: GatewayBus, machine_id: str) -> None:
        """Follow a machine first seen, on a worker thread: its first reads wait up to the
        timeout each on a frozen machine, and the loop serves the others' updates meanwhile."""
        try:
            attached = await asyncio.to_thread(bus.attach, machine_id, self._deliver())
        except Exception:  # logged; its token's next arrival tries again
            log.exception("event=attach_failed machine=%s", machine_id)
            return
        finally:
            again = self._attaching.pop(machine_id, False)
        if self.bus is not bus or machine_id not in self.space.machines:
            await asyncio.to_thread(attached.close)  # forgotten, or the gateway stopping
            return
        self.attached[machine_id] = attached
        if again:
            await self._refresh(attached)

    async def _refresh(self, attached: Attached) -> None:
        """A machine back from a drop-out: its current values read again (on a worker thread,
        the loop keeps serving), so what it publishes only on change is Good again too."""
        if self.bus is not None:
            try:
                await asyncio.to_thread(self.bus.refresh, attached, self._deliver())
            except Exception:  # a link closed under it (forgotten meanwhile): publications fill in
                log.exception("event=refresh_failed machine=%s", attached.machine_id)

    def _background(self, coro: Any) -> None:
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _deliver(self) -> Deliver:
        """For Zenoh's threads: hand an item to the loop and return at once."""
        loop = asyncio.get_running_loop()

        def deliver(machine_id: str, item: Any) -> None:
            with contextlib.suppress(RuntimeError):  # the loop closed while shutting down
                loop.call_soon_threadsafe(self._arrive, machine_id, item)

        return deliver

    async def _forget(self) -> None:
        """A machine gone for `forget_after_s` leaves the address space (its metrics stay,
        `ride_machine_alive` 0, so an alert on it can fire)."""
        while True:
            await asyncio.sleep(min(1.0, max(self.o.forget_after_s / 4, 0.05)))
            now = time.monotonic()
            for mid, view in list(self.views.items()):
                if view.left_at is not None and now - view.left_at >= self.o.forget_after_s:
                    view.left_at = None
                    attached = self.attached.pop(mid, None)
                    if attached is not None:
                        await asyncio.to_thread(attached.close)
                    if (node := self.space.machines.get(mid)) is not None:
                        for method in node.methods.values():
                            self.iserver.calls.unbind(method)
                    await self.space.remove(mid)

    # ----------------------------------------------------------------------- commands
    async def _send(self, machine_id: str, command: Command, request: CommandRequest) -> Reply:
        attached, bus = self.attached.get(machine_id), self.bus
        view = self.views.get(machine_id)
        if attached is None or bus is None or view is None or not view.alive:
            raise NoMachine(f"machine {machine_id} is not alive")
        timeout = self.o.command_timeout_s
        return await asyncio.to_thread(bus.command, attached, command, request, timeout)

    def _declare_rider(self, key: str, operator: str) -> Any:
        assert self.bus is not None
        return self.bus.supervise(key, operator)
