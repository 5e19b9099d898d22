"""asyncua as a client of the gateway: connect, find a machine, call its methods, subscribe."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from asyncua import Client, ua

from tests.gateway.support import NAMESPACE

T = TypeVar("T")


@dataclass(frozen=True)
class Called:
    """A method call's result as the client received it."""

    status: ua.StatusCode
    code: str
    message: str
    transaction_id: str
    state: str

    @property
    def good(self) -> bool:
        return bool(self.status.is_good())


@contextlib.asynccontextmanager
async def connected(
    url: str, user: str | None = None, password: str | None = None, **settings: Any
) -> AsyncIterator[Client]:
    client = Client(url, timeout=10)
    if user is not None:
        client.set_user(user)
        client.set_password(password or "")
    if "security" in settings:
        await client.set_security_string(settings["security"])
    async with client:
        yield client


async def ns(client: Client) -> int:
    return int(await client.get_namespace_index(NAMESPACE))


async def machines(client: Client) -> set[str]:
    idx = await ns(client)
    folder = client.get_node(ua.NodeId("gateway.Machines", idx))
    return {ref.BrowseName.Name for ref in await folder.get_children_descriptions()}


async def read(client: Client, machine_id: str, path: str) -> ua.DataValue:
    node = client.get_node(ua.NodeId(f"{machine_id}/{path}", await ns(client)))
    return await node.read_data_value(raise_on_bad_status=False)


async def call(client: Client, machine_id: str, method: str, *args: ua.Variant) -> Called:
    """A machine's method called on its own object."""
    idx = await ns(client)
    return await call_on(
        client, ua.NodeId(machine_id, idx), ua.NodeId(f"{machine_id}/{method}", idx), *args
    )


async def call_on(
    client: Client, object_id: ua.NodeId, method_id: ua.NodeId, *args: ua.Variant
) -> Called:
    """The call's whole result (status and output arguments), as the wire carries it: asyncua's
    `call_method` raises on a Bad status and drops the outputs."""
    request = ua.CallMethodRequest(
        ObjectId=object_id, MethodId=method_id, InputArguments=list(args)
    )
    (result,) = await client.uaclient.call([request])
    texts = [v.Value if isinstance(v.Value, str) else "" for v in result.OutputArguments]
    return Called(result.StatusCode, *[*texts, "", "", "", ""][:4])


class Changes:
    """A subscription's data changes, as (value, source timestamp, status) per node id string."""

    def __init__(self) -> None:
        self.values: asyncio.Queue[tuple[str, Any, Any, ua.StatusCode]] = asyncio.Queue()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        dv = data.monitored_item.Value
        status = dv.StatusCode or ua.StatusCode()
        self.values.put_nowait((node.nodeid.Identifier, val, dv.SourceTimestamp, status))

    async def _first(
        self, nodeid: str, ok: Callable[[Any, ua.StatusCode], bool], timeout: float
    ) -> Any:
        async with asyncio.timeout(timeout):
            while True:
                nid, val, when, status = await self.values.get()
                if nid == nodeid and ok(val, status):
                    return when

    async def until(self, nodeid: str, wanted: Any, timeout: float) -> Any:
        """The source timestamp of the first change of `nodeid` to `wanted` (Good)."""
        return await self._first(nodeid, lambda v, s: s.is_good() and v == wanted, timeout)

    async def good(self, nodeid: str, timeout: float) -> Any:
        """The first Good value of `nodeid`."""
        return await self._first(nodeid, lambda v, s: s.is_good(), timeout)

    async def status(self, nodeid: str, code: int, timeout: float) -> None:
        """Until `nodeid` is notified with the status `code`."""
        await self._first(nodeid, lambda v, s: s.value == code, timeout)


class Events:
    """A subscription's event notifications, in order."""

    def __init__(self) -> None:
        self.got: asyncio.Queue[Any] = asyncio.Queue()

    def event_notification(self, event: Any) -> None:
        self.got.put_nowait(event)

    async def first(self, ok: Callable[[Any], bool], timeout: float) -> Any:
        """The first event (from now on) `ok` accepts."""
        async with asyncio.timeout(timeout):
            while not ok(event := await self.got.get()):
                pass
            return event


def run(coro: Any) -> Any:
    return asyncio.run(coro)


async def eventually(
    what: str, probe: Callable[[], Awaitable[T | None]], timeout: float = 20.0
) -> T:
    """Await `probe` until it returns something (not None), bounded."""
    deadline = time.monotonic() + timeout
    while True:
        got = await probe()
        if got is not None:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        await asyncio.sleep(0.05)


async def variables(client: Client, machine_id: str) -> dict[str, ua.DataValue]:
    """Every data variable under the machine's object (its components, folders walked; no
    properties), by node id string, with the value each reads now (Bad ones included)."""
    idx = await ns(client)
    found: list[Any] = []
    todo = [client.get_node(ua.NodeId(machine_id, idx))]
    while todo:
        node = todo.pop()
        for ref in await node.get_children_descriptions(refs=ua.ObjectIds.HierarchicalReferences):
            if ref.ReferenceTypeId == ua.NodeId(ua.ObjectIds.HasProperty):
                continue
            child = client.get_node(ref.NodeId)
            if ref.NodeClass == ua.NodeClass.Variable:
                found.append(child)
            elif ref.NodeClass == ua.NodeClass.Object:
                todo.append(child)
    values = await client.read_attributes(found) if found else []
    return {str(n.nodeid.Identifier): dv for n, dv in zip(found, values, strict=True)}


def good(values: dict[str, ua.DataValue]) -> set[str]:
    return {nid for nid, dv in values.items() if dv.StatusCode is None or dv.StatusCode.is_good()}
