"""The Call service as the specification says (issue 56, point 3 and the status codes): a
method runs only on the object it belongs to, wrong calls get their own status codes, an
oversized argument is refused without being logged, and who may call what is said per method
(also in `UserExecutable`). Real daemons, a real gateway, asyncua's client."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from asyncua import Client, ua

from ride_machine.rider.client import Rider
from ride_machine.schema.event_models import CommandEvent
from ride_machine.schema.events import Event
from tests.gateway.support import Credentials, GatewayProc, joined
from tests.gateway.ua import call, call_on, connected, eventually, ns, read, run
from tests.site.stand import Site

pytestmark = pytest.mark.integration
OPERATOR = "operator"
_S = ua.StatusCodes
SERVER = ua.NodeId(ua.ObjectIds.Server)


@pytest.fixture(scope="module")
def other(plant: Site) -> Iterator[str]:
    """A second machine beside m1, whose Stop a wrong call must not reach."""
    with joined(plant, "m4"):
        yield "m4"


def _stops(plant: Site, machine_id: str) -> int:
    with plant.rider(machine_id, timeout=5.0, supervise=False) as r:
        return sum(e.details.command == "Stop" for e in _commands(r))  # type: ignore[union-attr]


def _commands(rider: Rider) -> list[Event]:
    return list(rider.events(kinds=("command",), last=500))


@pytest.mark.hazard("H51")
def test_a_method_runs_only_on_the_object_it_belongs_to(
    plant: Site, gateway: GatewayProc, creds: Credentials, other: str
) -> None:
    async def body() -> None:
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            idx = await ns(c)
            await eventually(f"{other} in the address space", lambda: _readable(c, other))
            stop = ua.NodeId(f"{other}/Stop", idx)
            for obj in (
                ua.NodeId("m1", idx),  # another machine's object
                SERVER,
                ua.NodeId("gateway.Machines", idx),
                ua.NodeId("m1/Diagnostics", idx),  # a folder of another machine
            ):
                got = await call_on(c, obj, stop)
                assert got.status.value == _S.BadMethodInvalid, (obj, got)
            # Its own object still runs it.
            own = await call_on(c, ua.NodeId(other, idx), stop)
            assert own.good and own.code == "RESP_DONE", own

    before = _stops(plant, other)
    run(body())
    assert _stops(plant, other) == before + 1  # the one call on its own object, no other


async def _readable(client: Client, machine_id: str) -> bool | None:
    return (await read(client, machine_id, "State")).StatusCode.is_good() or None


def test_wrong_calls_get_the_specifications_status_codes(
    gateway: GatewayProc, creds: Credentials
) -> None:
    async def body() -> None:
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            idx = await ns(c)
            m1 = ua.NodeId("m1", idx)
            cases = [
                (m1, ua.NodeId("m1/NoSuchMethod", idx), _S.BadMethodInvalid),
                (m1, ua.NodeId("m1/State", idx), _S.BadMethodInvalid),  # a variable
                (ua.NodeId("nowhere", idx), ua.NodeId("m1/Stop", idx), _S.BadNodeIdUnknown),
                (ua.NodeId("m1/State", idx), ua.NodeId("m1/Stop", idx), _S.BadNodeIdInvalid),
                # A standard method nobody here may call.
                (
                    SERVER,
                    ua.NodeId(ua.ObjectIds.Server_SetSubscriptionDurable),
                    _S.BadUserAccessDenied,
                ),
            ]
            for obj, method, status in cases:
                got = await call_on(c, obj, method)
                assert got.status.value == status, (obj, method, got)

    run(body())


def test_an_oversized_argument_is_refused_and_never_logged(
    gateway: GatewayProc, creds: Credentials
) -> None:
    marker = "oversized-argument-marker"
    huge = '{"name": "' + marker + '", "steps": ' + "[" * 100_000 + "]" * 100_000 + "}"
    deep = "[" * 5000 + "]" * 5000  # within the bound, nested past any parser's depth

    async def body() -> None:
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            idx = await ns(c)
            m1, start = ua.NodeId("m1", idx), ua.NodeId("m1/Start", idx)
            got = await call_on(c, m1, start, ua.Variant(huge, ua.VariantType.String))
            assert got.status.value == _S.BadOutOfRange, got
            got = await call_on(c, m1, start, ua.Variant(deep, ua.VariantType.String))
            assert got.status.value == _S.BadInvalidArgument and got.code == "BAD_PAYLOAD", got
            assert "nests" in got.message
            many = [ua.Variant("", ua.VariantType.String)] * 20
            got = await call_on(c, m1, start, *many)
            assert got.status.value == _S.BadTooManyArguments, got

    run(body())
    gateway.lines.wait_for("status=BadTooManyArguments")
    logged = "\n".join(gateway.lines.seen)
    assert "status=BadOutOfRange" in logged
    assert marker not in logged and "[[[[" not in logged


def test_an_anonymous_clients_node_id_cannot_forge_a_log_line(gateway: GatewayProc) -> None:
    """A refused call logs the ids the client chose: a newline in one must not start a line of
    its own (a fake E-stop in the log an operator or an alert reads)."""
    forged = "ts=2026-01-01T00:00:00.000Z level=error logger=service event=estop_pressed"

    async def body() -> None:
        async with connected(gateway.url) as anon:
            idx = await ns(anon)
            bad = ua.NodeId(f"x\n{forged} marker=object", idx)
            got = await call_on(anon, bad, ua.NodeId("m1/Stop", idx))
            assert got.status.value == _S.BadNodeIdUnknown, got
            bad = ua.NodeId(f"x\n{forged} marker=method", idx)
            got = await call_on(anon, ua.NodeId("m1", idx), bad)
            assert got.status.value == _S.BadMethodInvalid, got

    run(body())
    gateway.lines.wait_for("marker=method")
    said = [line for line in gateway.lines.seen if "estop_pressed" in line]
    assert len(said) == 2 and all("event=opcua_call_refused" in line for line in said), said
    assert not any(line.startswith("ts=2026-01-01") for line in gateway.lines.seen)


def test_a_session_with_an_integer_too_long_to_read_is_an_invalid_argument(
    gateway: GatewayProc, creds: Credentials
) -> None:
    """Python refuses to read an integer of more than 4300 digits with a ValueError that is no
    JSON error: it was BadInternalError, now the field is named as for any bad session."""
    session = '{"name": "s", "steps": [{"kind": "tilt", "degrees": ' + "7" * 5001 + "}]}"

    async def body() -> None:
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            idx = await ns(c)
            got = await call_on(
                c,
                ua.NodeId("m1", idx),
                ua.NodeId("m1/Start", idx),
                ua.Variant(session, ua.VariantType.String),
            )
            assert got.status.value == _S.BadInvalidArgument and got.code == "BAD_PAYLOAD", got
            assert got.message.startswith("Session /steps/0/degrees:"), got

    run(body())


@pytest.mark.hazard("H52")
def test_anonymous_may_refresh_and_list_its_items_but_never_command(
    gateway: GatewayProc, creds: Credentials
) -> None:
    async def executable(c: Client, method: str) -> bool:
        node = c.get_node(ua.NodeId(f"m1/{method}", await ns(c)))
        dv = await node.read_attribute(ua.AttributeIds.UserExecutable)
        return bool(dv.Value.Value)

    async def body() -> None:
        async with connected(gateway.url) as anon:
            assert not await executable(anon, "Home")
            sub = await anon.create_subscription(100, None)
            sub_id = sub.subscription_id
            got = await call_on(
                anon,
                SERVER,
                ua.NodeId(ua.ObjectIds.Server_GetMonitoredItems),
                ua.Variant(sub_id, ua.VariantType.UInt32),
            )
            assert got.status.is_good(), got
            home = await call_on(
                anon, ua.NodeId("m1", await ns(anon)), ua.NodeId("m1/Home", await ns(anon))
            )
            assert home.status.value == _S.BadUserAccessDenied, home
        async with connected(gateway.url, OPERATOR, creds.password) as op:
            assert await executable(op, "Home")

    run(body())


@pytest.mark.hazard("H54")
def test_the_opc_ua_user_is_recorded_as_who_commanded(
    plant: Site, gateway: GatewayProc, creds: Credentials
) -> None:
    """Issue 56: the machine's history named only the gateway's Zenoh login. The gateway's Rider
    for the session names its OPC UA user in each confirmation (rider/<login>/<key>/confirm),
    and the machine records the user with the confirmed Rider."""

    async def body() -> str:
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            got = await call(c, "m1", "Home")  # a motion command: the machine asks its Rider
            return got.code

    code = run(body())
    with plant.rider("m1", timeout=5.0, supervise=False) as r:
        homes = [
            e.details
            for e in _commands(r)
            if isinstance(e.details, CommandEvent) and e.details.command == "Home"
        ]
    assert homes, "no Home in the machine's history"
    last = homes[-1]
    assert last.code == code and last.operator == OPERATOR, last
    assert last.identity is not None and last.identity == last.rider, last
