"""The gateway's loop: a machine whose first reads hang (a frozen daemon whose token is still
there) must not hold up the other machines' statuses and alarms. A bus and an address space of
the test's own: the loop's order is what is pinned, not Zenoh or OPC UA."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

from ride_machine.rider.gateway.bus import Deliver
from ride_machine.rider.gateway.server import Gateway, Options
from ride_machine.schema.status import MachineState, Status

WAIT_S = 2.0


class _Node:
    methods: dict[Any, Any] = {}

    async def update(self, update: Any, snapshot: bool = False) -> None:
        pass

    async def presence(self, alive: bool) -> None:
        pass


class _Space:
    def __init__(self) -> None:
        self.machines: dict[str, _Node] = {}

    async def add(self, machine_id: str) -> _Node:
        node = self.machines[machine_id] = _Node()
        return node


class _Alarms:
    def __init__(self) -> None:
        self.statuses: list[str] = []

    async def status(self, machine_id: str, status: Status) -> None:
        self.statuses.append(machine_id)

    async def presence(self, machine_id: str, alive: bool, when: float) -> None:
        pass


class _Attached:
    def __init__(self, machine_id: str) -> None:
        self.machine_id = machine_id
        self.closed = False

    def close(self) -> None:
        self.closed = True


class _Bus:
    """`attach` of a frozen machine waits until `thaw` is set (as four reads of 2 s would)."""

    def __init__(self, frozen: str) -> None:
        self.frozen = frozen
        self.thaw = threading.Event()
        self.made: list[_Attached] = []

    def attach(self, machine_id: str, deliver: Deliver) -> _Attached:
        if machine_id == self.frozen:
            self.thaw.wait(10.0)
        self.made.append(_Attached(machine_id))
        return self.made[-1]


def _status(machine_id: str) -> Status:
    return Status(machine_id=machine_id, state=MachineState.IDLE, seq=1, cycle=1, time=1.0)


async def _until(what: str, probe: Any) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + WAIT_S
    while not probe():
        assert loop.time() < deadline, f"not within {WAIT_S} s: {what}"
        await asyncio.sleep(0.01)


def test_a_machine_whose_first_reads_hang_does_not_hold_up_the_others() -> None:
    async def body() -> None:
        gw = Gateway(Options(connect=[], zenoh_config=None))
        space, alarms, bus = _Space(), _Alarms(), _Bus(frozen="m1")
        gw.space, gw.alarms, gw.bus = space, alarms, bus  # type: ignore[assignment]
        consume = asyncio.create_task(gw._consume())
        try:
            gw._arrive("m1", True)
            gw._arrive("m2", True)
            gw._arrive("m2", _status("m2"))
            await _until("m2's status reaches its alarms", lambda: "m2" in alarms.statuses)
            await _until("m2 attached", lambda: "m2" in gw.attached)
            assert "m1" not in gw.attached
            bus.thaw.set()
            await _until("m1 attached once thawed", lambda: "m1" in gw.attached)
        finally:
            bus.thaw.set()
            consume.cancel()

    asyncio.run(body())


def test_a_machine_forgotten_while_attaching_is_let_go_when_the_attach_ends() -> None:
    async def body() -> None:
        gw = Gateway(Options(connect=[], zenoh_config=None))
        space, bus = _Space(), _Bus(frozen="m1")
        gw.space, gw.alarms, gw.bus = space, _Alarms(), bus  # type: ignore[assignment]
        consume = asyncio.create_task(gw._consume())
        try:
            gw._arrive("m1", True)
            await _until("m1 in the address space", lambda: "m1" in space.machines)
            del space.machines["m1"]  # as `_forget` does, its attach still under way
            bus.thaw.set()
            await _until("its link closed", lambda: bus.made and bus.made[0].closed)
            assert "m1" not in gw.attached and not gw._attaching
        finally:
            bus.thaw.set()
            consume.cancel()

    asyncio.run(body())
