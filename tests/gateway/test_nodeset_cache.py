"""The standard address space from the gateway's cache (rider/gateway/nodeset_cache.py): made
once by a child process, read on demand by every gateway after, and without a writable cache
directory built in memory as before. Real gateways, asyncua's client."""

from __future__ import annotations

from pathlib import Path

import pytest
from asyncua import ua

from tests.gateway.support import Credentials, running_gateway
from tests.gateway.ua import connected, run
from tests.site.stand import Site

pytestmark = pytest.mark.integration
_I = ua.ObjectIds


async def _standard_nodes(url: str) -> None:
    """What clients read of the standard space: the server's status, a type's method."""
    async with connected(url) as c:
        build = await c.get_node(ua.NodeId(_I.Server_ServerStatus_BuildInfo)).read_value()
        assert build.ProductName == "ride-machine gateway"
        condition = c.get_node(ua.NodeId(_I.ConditionType))
        refresh = await condition.get_child("0:ConditionRefresh")
        assert refresh.nodeid == ua.NodeId(_I.ConditionType_ConditionRefresh)
        assert (await c.nodes.server.read_browse_name()).Name == "Server"


def test_the_standard_nodes_come_from_a_cache_made_once(
    plant: Site, creds: Credentials, tmp_path: Path
) -> None:
    cache = tmp_path / "cache"
    with running_gateway(plant.rider_cmd(), creds, "--cache-dir", str(cache)) as first:
        (ready,) = cache.glob("opcua-nodeset-*/ready")
        run(_standard_nodes(first.url))
    made = {p.name: p.stat().st_mtime_ns for p in ready.parent.iterdir()}
    with running_gateway(plant.rider_cmd(), creds, "--cache-dir", str(cache)) as again:
        run(_standard_nodes(again.url))
    assert {p.name: p.stat().st_mtime_ns for p in ready.parent.iterdir()} == made  # read only


def test_without_a_writable_cache_the_gateway_builds_them_in_memory(
    plant: Site, creds: Credentials, tmp_path: Path
) -> None:
    blocked = tmp_path / "a-file"
    blocked.write_text("not a directory\n")
    with running_gateway(plant.rider_cmd(), creds, "--cache-dir", str(blocked / "x")) as gw:
        assert any("event=nodeset_cache_unavailable" in line for line in gw.lines.seen)
        run(_standard_nodes(gw.url))
