"""The gateway follows the site: machines that arrive get an object and metrics at once, one
that leaves is marked gone (Alive false, values Bad), then leaves the address space."""

from __future__ import annotations

import asyncio
import re
from typing import Any

import pytest
from asyncua import ua

from tests.gateway.support import FORGET_AFTER_S, GatewayProc, joined, until
from tests.gateway.ua import Changes, connected, eventually, machines, ns, read, run
from tests.site.stand import Site

pytestmark = pytest.mark.integration


def _alive(scrape: str) -> dict[str, float]:
    found = re.findall(r'^ride_machine_alive\{machine="([^"]+)"\} (\S+)$', scrape, re.M)
    return {mid: float(v) for mid, v in found}


@pytest.mark.hazard("H08", "H51")
def test_two_machines_arrive_and_one_leaves(plant: Site, gateway: GatewayProc) -> None:
    plant.start_daemons({"m2": "client", "m3": "client"})
    try:

        async def arrived() -> None:
            async with connected(gateway.url) as c:

                async def all_three() -> bool | None:
                    return {"m1", "m2", "m3"} <= await machines(c) or None

                await eventually("m2 and m3 in the address space", all_three)
                for mid in ("m2", "m3"):

                    async def state(mid: str = mid) -> str | None:
                        dv = await read(c, mid, "State")
                        return str(dv.Value.Value) if dv.StatusCode.is_good() else None

                    assert await eventually(f"{mid}/State readable", state)

        run(arrived())
        assert _alive(gateway.scrape()).keys() >= {"m1", "m2", "m3"}

        async def leaves() -> None:
            async with connected(gateway.url) as c:
                changes = Changes()
                sub = await c.create_subscription(50, changes)
                await sub.subscribe_data_change(c.get_node(ua.NodeId("m3/Alive", await ns(c))))
                await changes.until("m3/Alive", True, 10)
                await asyncio.to_thread(plant.daemons.pop("m3").stop)
                await changes.until("m3/Alive", False, 20)

                async def gone() -> bool | None:
                    return "m3" not in await machines(c) or None

                await eventually("m3 out of the address space", gone, FORGET_AFTER_S + 20)
                assert {"m1", "m2"} <= await machines(c)

        run(leaves())
        # Its metrics stay, alive 0: an alert on a machine gone can fire.
        until("m3 alive 0", lambda: _alive(gateway.scrape()).get("m3") == 0.0 or None)
        assert _alive(gateway.scrape())["m2"] == 1.0
    finally:
        for mid in ("m2", "m3"):
            if (daemon := plant.daemons.pop(mid, None)) is not None:
                daemon.stop()


def test_a_machine_may_be_called_machines(plant: Site, gateway: GatewayProc) -> None:
    """The gateway's own nodes have ids of their own (`gateway.Machines`): a machine whose id is
    `Machines` is a machine like any other (it never appeared: its object's id was the
    folder's)."""
    with joined(plant, "Machines"):

        async def listed() -> None:
            async with connected(gateway.url) as c:
                idx = await ns(c)
                folder = await c.nodes.objects.get_child(f"{idx}:Machines")

                async def there() -> bool | None:
                    names = {r.BrowseName.Name for r in await folder.get_children_descriptions()}
                    return "Machines" in names or None

                await eventually("a machine called Machines listed", there)
                dv = await eventually("its State", lambda: _good(read(c, "Machines", "State")))
                assert dv.Value.Value

        run(listed())


async def _good(pending: Any) -> ua.DataValue | None:
    dv = await pending
    return dv if dv.StatusCode.is_good() else None
