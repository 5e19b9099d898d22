"""A SCADA integrator's scripted session (issue 56, "Done when"), with two independent client
stacks at once — node-opcua (tests/gateway/js/integrator.mjs, a Node process) and asyncua's
client — against a gateway on a site of its own (a router, two machines):

browse by type, subscribe to values and alarms, call methods per machine, acknowledge; then a
token flap (a daemon frozen past its lease), a router outage of 10 s and a forget-and-return
(a machine gone past `--forget-after`): every value Good again within 2 s of the machine's
return, every subscription of both clients still delivering, and every alarm raised while the
asyncua client was away present after its ConditionRefresh.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua

from tests.gateway.support import Credentials, GatewayProc, running_gateway, until
from tests.gateway.test_alarms import acknowledge, alarm_list, refreshed, state
from tests.gateway.ua import (
    Changes,
    Events,
    call,
    connected,
    eventually,
    good,
    ns,
    read,
    run,
    variables,
)
from tests.nodejs import node_module
from tests.site.stand import Site, site

pytestmark = pytest.mark.integration
JS = Path(__file__).resolve().parent / "js"
OPERATOR = "operator"
FORGET_S = 14.0
"""Past a 10 s outage (the machines come back before it), short enough for a test."""
OUTAGE_S = 10.0
RETURN_BOUND_S = 2.0
MACHINES = ("i1", "i2")
WATCHED = ("Alive", "State", "TiltPosition", "Axes/tilt/PositionFeedback")


class NodeSession:
    """integrator.mjs as a child: the JSON lines it printed (all kept, in order), and commands
    on its stdin."""

    def __init__(self, url: str, password: str, home: Path) -> None:
        self.stderr = (home / "node.err").open("w")
        self.proc = subprocess.Popen(
            ["node", "integrator.mjs", url, OPERATOR, password],
            cwd=JS,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.stderr,
            text=True,
            env={**os.environ, "XDG_CONFIG_HOME": str(home), "HOME": str(home)},
        )
        self.seen: list[dict[str, Any]] = []
        self.ended = False
        self._new = threading.Condition()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith('{"t"'):  # node-opcua prints notices of its own
                with self._new:
                    self.seen.append(json.loads(line))
                    self._new.notify_all()
        with self._new:
            self.ended = True
            self._new.notify_all()

    def mark(self) -> int:
        """Where the lines printed from now on start."""
        with self._new:
            return len(self.seen)

    def send(self, **command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()

    def wait(
        self, what: str, ok: Callable[[dict[str, Any]], bool], since: int, timeout: float = 20
    ) -> tuple[int, dict[str, Any]]:
        """The first line from `since` on that `ok` accepts, and the index after it."""
        deadline = time.monotonic() + timeout
        with self._new:
            while True:
                for i in range(since, len(self.seen)):
                    if ok(self.seen[i]):
                        return i + 1, self.seen[i]
                since = len(self.seen)
                left = deadline - time.monotonic()
                if self.ended or left <= 0:
                    raise AssertionError(f"node-opcua: no {what} in {timeout:g} s")
                self._new.wait(left)

    def value(self, node: str, ok: Callable[[dict[str, Any]], bool], since: int) -> int:
        """After `since`, until a change of `node` that `ok` accepts; the index after it."""

        def change(line: dict[str, Any]) -> bool:
            return line["t"] == "value" and line["node"] == node and ok(line)

        return self.wait(f"a change of {node}", change, since)[0]

    def close(self) -> None:
        with contextlib.suppress(BrokenPipeError, OSError):
            self.send(do="quit")
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self.stderr.close()


@contextlib.contextmanager
def stand(tmp: Path, creds: Credentials) -> Iterator[tuple[Site, GatewayProc]]:
    (tmp / "site").mkdir()
    with site(tmp / "site") as s:
        s.start_daemons(dict.fromkeys(MACHINES, "client"))
        more = ("--forget-after", str(FORGET_S))
        with running_gateway(s.rider_cmd(), creds, *more) as gw:
            yield s, gw


async def by_type(client: Client) -> set[str]:
    idx = await ns(client)
    folder = client.get_node(ua.NodeId("gateway.Machines", idx))
    kind = ua.NodeId("gateway.RideMachineType", idx)
    refs = await folder.get_children_descriptions()
    return {r.BrowseName.Name for r in refs if r.TypeDefinition == kind}


async def all_good(client: Client, machine: str, before: set[str], since: float) -> float:
    """Seconds from `since` until every value of `machine` that was Good before is Good."""

    async def probe() -> set[str] | None:
        got = good(await variables(client, machine))
        return got if got >= before else None

    await eventually(f"every value of {machine} Good again", probe, 20)
    return time.monotonic() - since


async def each(
    changes: Changes, nodes: list[str], wanted: object, timeout: float
) -> dict[str, float]:
    """Until each of `nodes` was notified Good with `wanted`; when each was (monotonic)."""
    left, when = set(nodes), {}
    async with asyncio.timeout(timeout):
        while left:
            nid, value, _, status = await changes.values.get()
            if nid in left and status.is_good() and value == wanted:
                left.discard(nid)
                when[nid] = time.monotonic()
    return when


async def settled(client: Client, machine: str) -> set[str]:
    async def probe() -> set[str] | None:
        got = good(await variables(client, machine))
        return got if any("/IO/" in n for n in got) and any("/Axes/" in n for n in got) else None

    return await eventually(f"{machine} settled", probe, 20)


@pytest.mark.hazard("H55")
def test_an_integrators_session_with_two_stacks_through_flap_outage_and_forget(
    tmp_path: Path, creds: Credentials
) -> None:
    node_module("node-opcua-client", JS, node=True)
    with stand(tmp_path, creds) as (plant, gateway):
        integrator = NodeSession(gateway.url, creds.password, tmp_path)
        try:
            run(Scene(plant, gateway, creds, integrator).run())
        finally:
            integrator.close()


@dataclass
class Scene:
    """The session's parts: the site, the gateway, node-opcua's process, what was measured."""

    plant: Site
    gateway: GatewayProc
    creds: Credentials
    node: NodeSession
    before: dict[str, set[str]] = field(default_factory=dict)
    """Each machine's Good values before anything happened to it."""
    took: dict[str, float] = field(default_factory=dict)
    """Seconds from a machine's return until all its values were Good again, by drop-out."""

    def operator(self) -> Any:
        return connected(self.gateway.url, OPERATOR, self.creds.password)

    async def run(self) -> None:
        at, ready = await asyncio.to_thread(self.node.wait, "ready", _kind("ready"), 0, 60)
        assert sorted(ready["machines"]) == list(MACHINES)  # node-opcua found them by type
        async with self.operator() as c:
            assert await by_type(c) == set(MACHINES)
            self.before = {m: await settled(c, m) for m in MACHINES}
            changes = Changes()
            sub = await c.create_subscription(50, changes)
            idx = await ns(c)
            paths = [f"{m}/{p}" for m in MACHINES for p in WATCHED]
            await sub.subscribe_data_change([c.get_node(ua.NodeId(p, idx)) for p in paths])
            events, _ = await alarm_list(c)
            await self.methods_and_an_alarm(c, events, at)
            await self.flap(c, changes)
            await self.outage(c, changes)
        forgotten = await self.forget_while_away()
        await self.back(forgotten)
        print("\nvalues Good again after the return, s: " + json.dumps(self.took))
        assert all(t < RETURN_BOUND_S for t in self.took.values()), self.took

    async def methods_and_an_alarm(self, c: Client, events: Events, at: int) -> None:
        """Methods per machine from both stacks; an E-stop both see, acknowledged by one."""
        node, (i1, i2) = self.node, MACHINES
        for m in MACHINES:
            assert (await call(c, m, "Stop")).code == "RESP_DONE"
        node.send(do="call", machine=i2, method="Stop")
        at, stopped = await asyncio.to_thread(node.wait, "Stop", _kind("called"), at)
        assert stopped["status"] == "Good" and stopped["outputs"][0] == "RESP_DONE"
        with self.plant.rider(i1, timeout=5.0, supervise=False) as r:
            await asyncio.to_thread(r.sim, "estop", pressed=True)
        estop_id = f"{i1}/Alarms/Estop"
        raised = await events.first(lambda e: e.NodeId.Identifier == estop_id, 10)
        assert state(raised) == (True, False, True)
        at, seen = await asyncio.to_thread(node.wait, "the E-stop", _estop(True), at)
        assert seen["AckedState.Id"] is False
        node.send(do="ack", conditionId=seen["ConditionId"], eventId=seen["EventId"], comment="ok")
        at, acked = await asyncio.to_thread(node.wait, "ack", _kind("acked"), at)
        assert acked["status"] == "Good", acked
        ack = await events.first(lambda e: e.NodeId.Identifier == estop_id, 10)
        assert state(ack) == (True, True, True) and ack.ClientUserId == OPERATOR

    async def flap(self, c: Client, changes: Changes) -> None:
        """i1 frozen past its lease (its token goes), then thawed."""
        node, i1 = self.node, MACHINES[0]
        at = node.mark()
        daemon = self.plant.daemons[i1]
        daemon.proc.send_signal(signal.SIGSTOP)
        try:
            await changes.until(f"{i1}/Alive", False, 20)
        finally:
            daemon.proc.send_signal(signal.SIGCONT)
        await changes.until(f"{i1}/Alive", True, 20)
        self.took["flap"] = await all_good(c, i1, self.before[i1], time.monotonic())
        at = await asyncio.to_thread(node.value, f"{i1}/Alive", _is(False), at)
        await asyncio.to_thread(node.value, f"{i1}/State", _bad("BadNoCommunication"), at)
        await asyncio.to_thread(node.value, f"{i1}/State", _bad("Good"), at)

    async def outage(self, c: Client, changes: Changes) -> None:
        """The router out for 10 s: both machines gone, then back."""
        at = self.node.mark()
        self.plant.router.kill()
        alive = [f"{m}/Alive" for m in MACHINES]
        await each(changes, alive, False, 20)
        await asyncio.sleep(max(0.0, OUTAGE_S - 1.0))  # the outage itself, not a settle
        self.plant.router.start()
        returned = await each(changes, alive, True, 30)
        for m in MACHINES:
            self.took[f"outage {m}"] = await all_good(c, m, self.before[m], returned[f"{m}/Alive"])
        for m in MACHINES:
            gone = await asyncio.to_thread(self.node.value, f"{m}/Alive", _is(False), at)
            await asyncio.to_thread(self.node.value, f"{m}/Alive", _is(True), gone)
            await asyncio.to_thread(self.node.value, f"{m}/State", _bad("Good"), gone)

    async def forget_while_away(self) -> int:
        """With the asyncua client gone: i2 frozen until forgotten, and i1's E-stop released,
        reset (node-opcua sees it inactive) and pressed again. node-opcua's mark after its
        items on i2 were told BadNodeIdUnknown."""
        node, (i1, i2) = self.node, MACHINES
        at = node.mark()
        daemon = self.plant.daemons[i2]
        daemon.proc.send_signal(signal.SIGSTOP)
        try:
            removed = f"event=opcua_machine_removed machine={i2}"
            await asyncio.to_thread(self.gateway.lines.wait_for, removed, FORGET_S + 20)
            unknown = _bad("BadNodeIdUnknown")
            forgotten = await asyncio.to_thread(node.value, f"{i2}/State", unknown, at)
            with self.plant.rider(i1, timeout=5.0, supervise=False) as r:
                await asyncio.to_thread(r.sim, "estop", pressed=False)
                await asyncio.to_thread(until, "released", _released(r))
                await asyncio.to_thread(r.stop)
                await asyncio.to_thread(node.wait, "the E-stop reset", _estop(False), at)
                await asyncio.to_thread(r.sim, "estop", pressed=True)
        finally:
            daemon.proc.send_signal(signal.SIGCONT)
        return forgotten

    async def back(self, forgotten: int) -> None:
        """i2 back under its node ids; the asyncua client back, refreshing its alarm list."""
        node, (i1, i2) = self.node, MACHINES
        async with self.operator() as c:

            async def alive() -> float | None:
                dv = await read(c, i2, "Alive")
                return time.monotonic() if dv.StatusCode.is_good() and dv.Value.Value else None

            returned = await eventually(f"{i2} back", alive, 30)
            self.took["forget"] = await all_good(c, i2, self.before[i2], returned)
            events, alarms = await alarm_list(c)
            listed = await refreshed(c, alarms, events)
            assert state(listed[f"{i1}/Alarms/Estop"]) == (True, False, True)  # raised again
            lost = listed[f"{i2}/Alarms/Lost"]
            assert state(lost) == (False, False, True)  # gone and back, not acknowledged
            assert (await acknowledge(c, lost, "back")).is_good()
        # node-opcua stayed connected: its items on the forgotten machine deliver again.
        await asyncio.to_thread(node.value, f"{i2}/State", _bad("Good"), forgotten)
        listed_by_node = await asyncio.to_thread(_node_refresh, node)
        assert f"{i1}/Alarms/Estop" in listed_by_node
        assert f"{i2}/Alarms/Lost" not in listed_by_node  # acknowledged, back: not retained


def _node_refresh(node: NodeSession) -> set[str]:
    """node-opcua's ConditionRefresh: the ConditionIds between RefreshStart and RefreshEnd."""
    at = node.mark()
    node.send(do="refresh")
    _, answer = node.wait("the refresh", _kind("refreshed"), at)
    assert answer["status"] == "Good", answer
    at, _ = node.wait("RefreshStart", _event_type(2787), at)
    end, _ = node.wait("RefreshEnd", _event_type(2788), at)
    return {
        str(line["ConditionId"]).partition(";s=")[2]
        for line in node.seen[at : end - 1]
        if line["t"] == "event" and line["ConditionId"]
    }


def _kind(kind: str) -> Callable[[dict[str, Any]], bool]:
    return lambda line: line["t"] == kind


def _is(value: object) -> Callable[[dict[str, Any]], bool]:
    return lambda line: line["status"] == "Good" and line["value"] is value


def _bad(status: str) -> Callable[[dict[str, Any]], bool]:
    return lambda line: line["status"] == status


def _event_type(number: int) -> Callable[[dict[str, Any]], bool]:
    return lambda line: line["t"] == "event" and line["EventType"] == f"ns=0;i={number}"


def _estop(active: bool) -> Callable[[dict[str, Any]], bool]:
    """An Estop condition's event, active or not."""

    def ok(line: dict[str, Any]) -> bool:
        return (
            line["t"] == "event"
            and line["ConditionName"] == "Estop"
            and (line["ActiveState.Id"] is active)
        )

    return ok


def _released(rider: Any) -> Callable[[], bool | None]:
    return lambda: not rider.status().estop.active or None
