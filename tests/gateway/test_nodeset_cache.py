"""The standard address space from the gateway's cache (rider/gateway/nodeset_cache.py): made
once by a child process, read on demand by every gateway after, and without a writable cache
directory built in memory as before. Real gateways, asyncua's client."""

from __future__ import annotations

import os
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


def test_without_a_user_cache_the_temp_directory_serves(
    plant: Site, creds: Credentials, tmp_path: Path
) -> None:
    """A read-only root (a container's): the user's cache cannot be made; a tmpfs /tmp can."""
    blocked = tmp_path / "a-file"
    blocked.write_text("not a directory\n")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {"XDG_CACHE_HOME": str(blocked / "cache"), "TMPDIR": str(tmp)}
    with running_gateway(plant.rider_cmd(), creds, env=env) as gw:
        assert any("event=nodeset_cache_unavailable" in line for line in gw.lines.seen)
        assert len(list(tmp.glob(f"ride-machine-{os.getuid()}/opcua-nodeset-*/ready"))) == 1
        run(_standard_nodes(gw.url))


def test_a_cache_others_may_write_is_never_read(
    plant: Site, creds: Credentials, tmp_path: Path
) -> None:
    """Its files are pickles (loading one runs it): a directory others may write is refused,
    and the standard nodes are built in memory."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    with running_gateway(plant.rider_cmd(), creds, "--cache-dir", str(shared)) as gw:
        assert any(
            "event=nodeset_cache_unavailable" in line and "alone" in line for line in gw.lines.seen
        )
        assert not list(shared.glob("*/ready"))
        run(_standard_nodes(gw.url))
