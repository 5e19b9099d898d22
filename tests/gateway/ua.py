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
    folder = client.get_node(ua.NodeId("Machines", idx))
    return {ref.BrowseName.Name for ref in await folder.get_children_descriptions()}


async def read(client: Client, machine_id: str, path: str) -> ua.DataValue:
    node = client.get_node(ua.NodeId(f"{machine_id}/{path}", await ns(client)))
    return await node.read_data_value(raise_on_bad_status=False)


async def call(client: Client, machine_id: str, method: str, *args: ua.Variant) -> Called:
    """The call's whole result (status and output arguments), as the wire carries it: asyncua's
    `call_method` raises on a Bad status and drops the outputs."""
    idx = await ns(client)
    request = ua.CallMethodRequest(
        ObjectId=ua.NodeId(machine_id, idx),
        MethodId=ua.NodeId(f"{machine_id}/{method}", idx),
        InputArguments=list(args),
    )
    (result,) = await client.uaclient.call([request])
    outputs = [v.Value for v in result.OutputArguments] or ["", "", "", ""]
    return Called(result.StatusCode, *outputs)


class Changes:
    """A subscription's data changes, as (value, source timestamp) per node id string."""

    def __init__(self) -> None:
        self.values: asyncio.Queue[tuple[str, Any, Any]] = asyncio.Queue()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        dv = data.monitored_item.Value
        self.values.put_nowait((node.nodeid.Identifier, val, dv.SourceTimestamp))

    async def until(self, nodeid: str, wanted: Any, timeout: float) -> Any:
        """The source timestamp of the first change of `nodeid` to `wanted`."""
        async with asyncio.timeout(timeout):
            while True:
                nid, val, when = await self.values.get()
                if nid == nodeid and val == wanted:
                    return when


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
