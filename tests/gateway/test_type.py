"""The address space a SCADA engineer builds on (issue 56, "What to build"): every machine a
`RideMachineType`, string node ids for every node, the same on a restarted gateway and for a
machine that joined later; analog values as `AnalogItemType` with `EURange` (a PercentDeadband
only there); the product's own identity, its limits written and enforced; ServerTimestamp as
asked. A real gateway, asyncua's client."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from asyncua import Client, ua

from tests.gateway.support import Credentials, GatewayProc, joined, running_gateway
from tests.gateway.ua import connected, eventually, ns, run
from tests.site.stand import Site

pytestmark = pytest.mark.integration
_S = ua.StatusCodes
_I = ua.ObjectIds
TYPE = "gateway.RideMachineType"


@pytest.fixture(scope="module")
def later(plant: Site) -> Iterator[str]:
    """A machine that joins after m1."""
    with joined(plant, "m5"):
        yield "m5"


async def subtree(client: Client, root: ua.NodeId) -> dict[str, ua.NodeId]:
    """Every node below `root` (properties too) by its node id, with its type definition."""
    found: dict[str, ua.NodeId] = {}
    todo = [client.get_node(root)]
    while todo:
        node = todo.pop()
        for ref in await node.get_children_descriptions(refs=_I.HierarchicalReferences):
            assert ref.NodeId.NodeIdType is ua.NodeIdType.String, ref.NodeId
            found[ref.NodeId.Identifier] = ref.TypeDefinition
            todo.append(client.get_node(ref.NodeId))
    return found


def relative(ids: dict[str, ua.NodeId], prefix: str) -> dict[str, ua.NodeId]:
    assert all(i.startswith(f"{prefix}/") for i in ids), ids
    return {i.removeprefix(f"{prefix}/"): t for i, t in ids.items() if "/IO/" not in f"/{i}"}


def test_machines_are_ride_machine_types_with_the_same_string_ids_on_every_gateway(
    plant: Site, gateway: GatewayProc, creds: Credentials, later: str
) -> None:
    async def shape(url: str) -> tuple[dict[str, ua.NodeId], dict[str, ua.NodeId]]:
        async with connected(url) as c:
            idx = await ns(c)
            await eventually(f"{later} listed", lambda: _there(c, ua.NodeId(f"{later}/State", idx)))
            machine_type = c.get_node(ua.NodeId(TYPE, idx))
            (base,) = await machine_type.get_referenced_nodes(
                _I.HasSubtype, ua.BrowseDirection.Inverse
            )
            assert base.nodeid == ua.NodeId(_I.BaseObjectType)
            for mid in ("m1", later):
                definition = await c.get_node(ua.NodeId(mid, idx)).read_type_definition()
                assert definition == machine_type.nodeid
            declared = relative(await subtree(c, machine_type.nodeid), TYPE)
            first = relative(await subtree(c, ua.NodeId("m1", idx)), "m1")
            assert relative(await subtree(c, ua.NodeId(later, idx)), later) == first
            return declared, first

    declared, first = run(shape(gateway.url))
    # Every instance declaration is there, of the type it declares (IO is each machine's own).
    assert {k: v for k, v in first.items() if not k.startswith("IO/")} == {
        k: v for k, v in declared.items() if not k.startswith("IO/")
    }
    assert {"Start/InputArguments", "TiltPosition/EURange", "Uptime/EngineeringUnits"} <= set(first)
    # A gateway started now (m5 and m1 both there before it) names every node the same.
    with running_gateway(plant.rider_cmd(), creds) as again:
        assert run(shape(again.url))[1] == first


async def _there(client: Client, nid: ua.NodeId) -> bool | None:
    dv = await client.get_node(nid).read_data_value(raise_on_bad_status=False)
    return dv.StatusCode.is_good() or None


def test_analog_values_carry_their_range_and_take_a_percent_deadband(gateway: GatewayProc) -> None:
    async def body() -> None:
        async with connected(gateway.url) as c:
            idx = await ns(c)
            tilt = c.get_node(ua.NodeId("m1/TiltPosition", idx))
            assert await tilt.read_type_definition() == ua.NodeId(_I.AnalogItemType)
            span = await c.get_node(ua.NodeId("m1/TiltPosition/EURange", idx)).read_value()
            assert isinstance(span, ua.Range) and span.Low < 0 and span.High > 60  # tilt.max_deg
            sub = await c.create_subscription(100, None)
            nodes = [
                tilt,
                c.get_node(ua.NodeId("m1/StatusSeq", idx)),  # a number without a range
                c.get_node(ua.NodeId("m1/State", idx)),  # no number at all
            ]
            got = await sub.deadband_monitor(nodes, 5.0, ua.DeadbandType.Percent)
            assert isinstance(got[0], int), got
            assert [g.value for g in got[1:]] == [  # type: ignore[union-attr]
                _S.BadDeadbandFilterInvalid,
                _S.BadFilterNotAllowed,
            ]

    run(body())


def test_the_server_says_what_it_is_and_gives_timestamps_as_asked(gateway: GatewayProc) -> None:
    async def body() -> None:
        async with connected(gateway.url) as c:
            build = await c.get_node(ua.NodeId(_I.Server_ServerStatus_BuildInfo)).read_value()
            assert build.ProductName == "ride-machine gateway", build
            assert build.ManufacturerName == "ride-machine" and "FreeOpcUa" not in str(build)
            assert build.ProductUri == "urn:ride-machine:product:gateway"
            assert build.SoftwareVersion and build.BuildDate.year > 2000
            caps = _I.Server_ServerCapabilities_MaxSessions
            assert await c.get_node(ua.NodeId(caps)).read_value() == 50
            node = ua.NodeId("m1/State", await ns(c))
            T = ua.TimestampsToReturn
            for asked, source, server in (
                (T.Both, True, True),
                (T.Server, False, True),
                (T.Source, True, False),
                (T.Neither, False, False),
            ):
                rv = ua.ReadValueId(NodeId=node, AttributeId=ua.AttributeIds.Value)
                params = ua.ReadParameters(NodesToRead=[rv], TimestampsToReturn=asked)
                (dv,) = await c.uaclient.read(params)
                assert (dv.SourceTimestamp is not None, dv.ServerTimestamp is not None) == (
                    source,
                    server,
                ), asked

    run(body())


def test_sessions_past_the_limit_are_refused(plant: Site, creds: Credentials) -> None:
    with running_gateway(plant.rider_cmd(), creds, "--max-sessions", "2") as gw:

        async def body() -> None:
            async with connected(gw.url) as one, connected(gw.url):
                limit = _I.Server_ServerCapabilities_MaxSessions
                assert await one.get_node(ua.NodeId(limit)).read_value() == 2
                with pytest.raises(ua.uaerrors.BadTooManySessions):
                    async with connected(gw.url):
                        pass
            async with connected(gw.url):  # room again once one went
                pass

        run(body())
