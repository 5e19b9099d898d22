"""The gateway's OPC UA server against asyncua's client in this process: browse, read,
subscribe, methods and their refusals, who may call, the encrypted endpoint."""

from __future__ import annotations

import asyncio
import time
from datetime import UTC, datetime

import pytest
from asyncua import ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from ride_machine.rider.client import Rider
from tests.gateway.support import (
    Credentials,
    GatewayProc,
    until,
)
from tests.gateway.ua import Changes, Events, call, connected, machines, ns, read, run
from tests.site.stand import Site

pytestmark = pytest.mark.integration
OPERATOR = "operator"
_S = ua.StatusCodes


@pytest.mark.hazard("H51")
def test_an_operator_browses_reads_subscribes_and_calls(
    gateway: GatewayProc, creds: Credentials
) -> None:
    async def body() -> None:
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            assert "m1" in await machines(c)
            assert (await call(c, "m1", "Stop")).code == "RESP_DONE"
            changes = Changes()
            sub = await c.create_subscription(50, changes)
            await sub.subscribe_data_change(c.get_node(ua.NodeId("m1/State", await ns(c))))
            await changes.until("m1/State", "DONE", 10)

            home = await call(c, "m1", "Home")
            assert home.good and home.code == "RESP_HOME_ACCEPTED", home
            assert home.state == "HOMING" and home.transaction_id
            when = await changes.until("m1/State", "HOMING", 10)
            # The machine's own time of the status that said it, as its source timestamp.
            assert abs((datetime.now(UTC) - when).total_seconds()) < 10

            start = await call(c, "m1", "Start", ua.Variant("", ua.VariantType.String))
            assert start.status.value == _S.BadInvalidState, start
            assert start.code == "WRONG_STATE" and "Start" in start.message, start
            assert (await call(c, "m1", "Stop")).good

            state = await read(c, "m1", "State")
            assert state.StatusCode.is_good() and state.Value.Value in {"DONE", "HOMING"}
            position = c.get_node(ua.NodeId("m1/TiltPosition", await ns(c)))
            eu = await position.get_child("0:EngineeringUnits")
            assert (await eu.read_value()).DisplayName.Text == "°"

    run(body())


@pytest.mark.hazard("H52")
def test_anonymous_reads_and_browses_but_never_calls(gateway: GatewayProc) -> None:
    async def body() -> None:
        async with connected(gateway.url) as c:
            assert "m1" in await machines(c)
            before = await read(c, "m1", "State")
            assert before.StatusCode.is_good()
            home = await call(c, "m1", "Home")
            assert home.status.value == _S.BadUserAccessDenied, home
            assert (await read(c, "m1", "State")).Value.Value == before.Value.Value

    run(body())


@pytest.mark.hazard("H52")
def test_a_wrong_password_is_refused(gateway: GatewayProc) -> None:
    async def body() -> None:
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with connected(gateway.url, OPERATOR, "not-the-password"):
                pass
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with connected(gateway.url, "nobody", "x"):
                pass

    run(body())


def test_a_bad_argument_is_a_clear_bad_status_and_the_machine_keeps_cycling(
    gateway: GatewayProc, creds: Credentials
) -> None:
    async def body() -> None:
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            cycles = (await read(c, "m1", "Diagnostics/Cycles")).Value.Value
            cases = [
                ("Start", ua.Variant(5, ua.VariantType.Int32), _S.BadTypeMismatch, "String"),
                (
                    "Start",
                    ua.Variant("{oops", ua.VariantType.String),
                    _S.BadInvalidArgument,
                    "not JSON",
                ),
                (
                    "Start",
                    ua.Variant('{"steps": []}', ua.VariantType.String),
                    _S.BadInvalidArgument,
                    "/steps",
                ),
                ("Home", ua.Variant("x", ua.VariantType.String), _S.BadTooManyArguments, "Home"),
            ]
            for method, arg, status, text in cases:
                got = await call(c, "m1", method, arg)
                assert got.status.value == status, got
                assert got.code == "BAD_PAYLOAD" and text in got.message, got
            deadline = time.monotonic() + 20
            while (await read(c, "m1", "Diagnostics/Cycles")).Value.Value <= cycles:
                assert time.monotonic() < deadline, "the scan loop stopped cycling"
                await asyncio.sleep(0.1)

    run(body())


def test_the_encrypted_endpoint_uses_the_certificate_credentials_init_made(
    gateway: GatewayProc, creds: Credentials, client_certs: tuple[Credentials, Credentials]
) -> None:
    client_creds = client_certs[1]  # an application certificate that is no operator's

    async def body() -> None:
        async with connected(gateway.url) as c:
            endpoints = await c.get_endpoints()
        secure = [
            e
            for e in endpoints
            if e.SecurityPolicyUri == SecurityPolicyBasic256Sha256.URI
            and e.SecurityMode == ua.MessageSecurityMode.SignAndEncrypt
        ]
        assert secure and secure[0].ServerCertificate == creds.certificate.read_bytes()
        security = ",".join(
            [
                "Basic256Sha256",
                "SignAndEncrypt",
                str(client_creds.certificate),
                str(client_creds.private_key),
                str(creds.certificate),
            ]
        )
        async with connected(gateway.url, OPERATOR, creds.password, security=security) as c:
            assert (await call(c, "m1", "Stop")).code == "RESP_DONE"

    run(body())


@pytest.mark.hazard("H52")
def test_a_listed_certificate_is_an_operator_an_unlisted_one_only_reads(
    gateway: GatewayProc, creds: Credentials, client_certs: tuple[Credentials, Credentials]
) -> None:
    listed, unlisted = client_certs

    def security(client: Credentials) -> str:
        parts = [client.certificate, client.private_key, creds.certificate]
        return ",".join(["Basic256Sha256", "SignAndEncrypt", *map(str, parts)])

    async def body() -> None:
        async with connected(gateway.url, security=security(listed)) as c:
            assert (await call(c, "m1", "Stop")).code == "RESP_DONE"
        async with connected(gateway.url, security=security(unlisted)) as c:
            assert (await read(c, "m1", "State")).StatusCode.is_good()
            stop = await call(c, "m1", "Stop")
            assert stop.status.value == _S.BadUserAccessDenied, stop

    run(body())


def test_an_estop_is_an_opc_ua_event_on_the_machine_with_a_severity(
    plant: Site, gateway: GatewayProc
) -> None:
    async def body() -> None:
        async with connected(gateway.url) as c:  # anonymous: events are read access
            idx = await ns(c)
            etype = await c.nodes.base_event_type.get_child(f"{idx}:MachineEventType")
            events = Events()
            sub = await c.create_subscription(50, events)
            await sub.subscribe_events(c.get_node(ua.NodeId("m1", idx)), etype)
            with plant.rider("m1", timeout=5.0, supervise=False) as r:
                await asyncio.to_thread(r.sim, "estop", pressed=True)
                try:
                    async with asyncio.timeout(20):
                        while (ev := await events.got.get()).Kind != "estop_pressed":
                            pass
                finally:
                    await asyncio.to_thread(r.sim, "estop", pressed=False)
                    await asyncio.to_thread(_released, r)
                    await asyncio.to_thread(r.stop)
            assert ev.Severity == 900 and ev.Code == "ESTOP" and ev.Machine == "m1"
            assert ev.SourceName == "m1" and "E-stop" in ev.Message.Text

    run(body())


def _released(rider: Rider) -> None:
    """Until the scan has seen the E-stop released (Stop is refused before)."""
    until("E-stop released", lambda: not rider.status().estop.active or None)
