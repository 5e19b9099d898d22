"""Alarms & Conditions (issue 56, point 5): an E-stop, a fault, a machine lost are
`AlarmConditionType` conditions with Active/Acked/Retain; a SCADA that connects after they were
raised sees them on `ConditionRefresh`; the operator acknowledges, the anonymous role may read
and refresh but never acknowledge. Real daemons, a real gateway, asyncua's client."""

from __future__ import annotations

import asyncio
import signal
from typing import Any

import pytest
from asyncua import Client, ua

from tests.gateway.support import Credentials, GatewayProc, joined, until
from tests.gateway.ua import Events, connected, ns, read, run
from tests.site.stand import Site

pytestmark = pytest.mark.integration
_S = ua.StatusCodes
_I = ua.ObjectIds
OPERATOR = "operator"
START = ua.NodeId(_I.RefreshStartEventType)
END = ua.NodeId(_I.RefreshEndEventType)


async def alarm_list(client: Client) -> tuple[Events, Any]:
    """Events of AlarmConditionType (and subtypes) from the Server object, as a SCADA's alarm
    list subscribes."""
    events = Events()
    sub = await client.create_subscription(50, events)
    await sub.subscribe_events(client.nodes.server, _I.AlarmConditionType)
    return events, sub


async def refreshed(client: Client, sub: Any, events: Events) -> dict[str, Any]:
    """`ConditionRefresh` on the subscription: the conditions between RefreshStart and
    RefreshEnd, by ConditionId."""
    request = ua.CallMethodRequest(
        ObjectId=ua.NodeId(_I.ConditionType),
        MethodId=ua.NodeId(_I.ConditionType_ConditionRefresh),
        InputArguments=[ua.Variant(sub.subscription_id, ua.VariantType.UInt32)],
    )
    (result,) = await client.uaclient.call([request])
    assert result.StatusCode.is_good(), result.StatusCode
    await events.first(lambda e: e.EventType == START, 10)
    got: dict[str, Any] = {}
    async with asyncio.timeout(10):
        while (event := await events.got.get()).EventType != END:
            got[event.NodeId.Identifier] = event
    return got


async def acknowledge(client: Client, condition: Any, comment: str) -> ua.StatusCode:
    request = ua.CallMethodRequest(
        ObjectId=condition.NodeId,
        MethodId=ua.NodeId(_I.AcknowledgeableConditionType_Acknowledge),
        InputArguments=[
            ua.Variant(condition.EventId, ua.VariantType.ByteString),
            ua.Variant(ua.LocalizedText(comment), ua.VariantType.LocalizedText),
        ],
    )
    (result,) = await client.uaclient.call([request])
    return result.StatusCode


def state(event: Any) -> tuple[bool, bool, bool]:
    """(active, acknowledged, retained)."""
    return getattr(event, "ActiveState/Id"), getattr(event, "AckedState/Id"), event.Retain


@pytest.mark.hazard("H52", "H55")
def test_an_estop_raised_while_scada_was_away_is_in_its_alarm_list_after_a_refresh(
    plant: Site, gateway: GatewayProc, creds: Credentials
) -> None:
    condition = "stopped/Alarms/Estop"
    with joined(plant, "stopped"), plant.rider("stopped", timeout=5.0, supervise=False) as r:
        r.sim("estop", pressed=True)
        until("E-stop latched", lambda: r.status().estop.latched or None)

        async def away() -> None:
            async with connected(gateway.url) as look:  # until the gateway has seen it

                async def latched() -> bool | None:
                    dv = await read(look, "stopped", "EstopLatched")
                    return (dv.StatusCode.is_good() and dv.Value.Value) or None

                await asyncio.wait_for(_poll(latched), 20)
            # A SCADA that was not connected when it was pressed.
            async with connected(gateway.url) as anon:
                events, sub = await alarm_list(anon)
                estop = (await refreshed(anon, sub, events))[condition]
                assert state(estop) == (True, False, True)
                assert estop.Severity == 900 and estop.SourceName == "stopped"
                assert estop.ConditionName == "Estop" and "E-stop" in estop.Message.Text
                assert estop.SourceNode == ua.NodeId("stopped", await ns(anon))
                # Anonymous may read and refresh, never acknowledge.
                refused = await acknowledge(anon, estop, "seen")
                assert refused.value == _S.BadUserAccessDenied, refused
            async with connected(gateway.url, OPERATOR, creds.password) as op:
                events, sub = await alarm_list(op)
                estop = (await refreshed(op, sub, events))[condition]
                assert state(estop) == (True, False, True)  # not acknowledged by the refusal
                assert (await acknowledge(op, estop, "checking the ride")).is_good()
                acked = await events.first(lambda e: e.NodeId.Identifier == condition, 10)
                assert state(acked) == (True, True, True)  # still active: still listed
                assert acked.ClientUserId == OPERATOR and acked.Comment.Text == "checking the ride"
                again = await acknowledge(op, acked, "twice")
                assert again.value == _S.BadConditionBranchAlreadyAcked, again
                stale = await acknowledge(op, estop, "an old event")
                assert stale.value == _S.BadEventIdUnknown, stale
                # Released and reset: inactive and acknowledged, it leaves the list.
                await asyncio.to_thread(r.sim, "estop", pressed=False)
                await asyncio.to_thread(
                    until, "released", lambda: not r.status().estop.active or None
                )
                await asyncio.to_thread(r.stop)
                gone = await events.first(
                    lambda e: e.NodeId.Identifier == condition and not e.Retain, 10
                )
                assert state(gone) == (False, True, False)
                assert condition not in await refreshed(op, sub, events)

        run(away())


@pytest.mark.hazard("H55")
def test_a_lost_machine_is_an_alarm_until_it_returns_and_is_acknowledged(
    plant: Site, gateway: GatewayProc, creds: Credentials
) -> None:
    condition = "vanished/Alarms/Lost"
    with joined(plant, "vanished") as daemon:
        gateway.lines.wait_for("event=machine_seen machine=vanished", 20)
        daemon.proc.send_signal(signal.SIGSTOP)  # frozen past its lease: the token goes
        try:
            gateway.lines.wait_for("event=machine_gone machine=vanished", 20)
        finally:
            daemon.proc.send_signal(signal.SIGCONT)

        async def later() -> None:
            async with connected(gateway.url, OPERATOR, creds.password) as op:
                events, sub = await alarm_list(op)

                async def back() -> bool | None:
                    alive = await read(op, "vanished", "Alive")
                    return (alive.StatusCode.is_good() and alive.Value.Value) or None

                await asyncio.wait_for(_poll(back), 30)
                lost = (await refreshed(op, sub, events))[condition]
                # Back, so inactive; not yet acknowledged, so still listed.
                assert state(lost) == (False, False, True) and lost.Severity == 800
                assert (await acknowledge(op, lost, "restarted the switch")).is_good()
                done = await events.first(lambda e: e.NodeId.Identifier == condition, 10)
                assert state(done) == (False, True, False)

        run(later())


async def _poll(probe: Any) -> Any:
    while (got := await probe()) is None:
        await asyncio.sleep(0.05)
    return got


def test_a_session_refreshes_only_its_own_subscriptions(gateway: GatewayProc) -> None:
    async def body() -> None:
        async with connected(gateway.url) as mine, connected(gateway.url) as other:
            _, theirs = await alarm_list(other)
            _, own = await alarm_list(mine)

            async def refresh(method: int, *args: ua.Variant) -> int:
                request = ua.CallMethodRequest(
                    ObjectId=ua.NodeId(_I.ConditionType),
                    MethodId=ua.NodeId(method),
                    InputArguments=list(args),
                )
                (result,) = await mine.uaclient.call([request])
                return int(result.StatusCode.value)

            def u32(value: int) -> ua.Variant:
                return ua.Variant(value, ua.VariantType.UInt32)

            refresh1, refresh2 = (
                _I.ConditionType_ConditionRefresh,
                _I.ConditionType_ConditionRefresh2,
            )
            assert await refresh(refresh1, u32(theirs.subscription_id)) == (
                _S.BadSubscriptionIdInvalid
            )
            assert await refresh(refresh1, u32(own.subscription_id)) == _S.Good
            assert await refresh(refresh2, u32(own.subscription_id), u32(999_999)) == (
                _S.BadMonitoredItemIdInvalid
            )
            assert await refresh(refresh1) == _S.BadArgumentsMissing

    run(body())
