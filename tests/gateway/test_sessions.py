"""What the gateway reads or changes inside asyncua (its session registry, its address space's
monitored items), pinned here against a real asyncua server: an asyncua release that moves
them fails these tests, not a ride."""

from __future__ import annotations

import asyncio

from asyncua import Client, Server, ua

from ride_machine.rider.gateway.parking import Parking
from ride_machine.rider.gateway.security import Rules, Users
from ride_machine.rider.gateway.supervision import open_session_keys
from tests.gateway.ua import Changes
from tests.procs import free_port


def test_open_session_keys_follows_sessions_opening_and_closing() -> None:
    async def body() -> None:
        server = Server(user_manager=Users({"operator": "pw"}, {}))
        await server.init()
        port = free_port()
        server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity], permission_ruleset=Rules())
        await server.start()
        try:
            assert open_session_keys(server.iserver) == set()
            client = Client(f"opc.tcp://127.0.0.1:{port}/", timeout=10)
            client.set_user("operator")
            client.set_password("pw")
            async with client:
                keys = open_session_keys(server.iserver)
                assert len(keys) == 1 and all(k.isalnum() for k in keys)  # a Rider id
            for _ in range(100):
                if not open_session_keys(server.iserver):
                    break
                await asyncio.sleep(0.02)
            assert open_session_keys(server.iserver) == set()
        finally:
            await server.stop()

    asyncio.run(body())


def test_monitored_items_parked_with_a_deleted_node_deliver_again_when_it_returns() -> None:
    """rider/gateway/parking.py reaches into asyncua's address space: a node deleted and made
    again under its id gets back the items a client had on it; one deleted meanwhile is gone."""

    async def body() -> None:
        server = Server()
        await server.init()
        port = free_port()
        server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        parking = Parking(server.iserver.aspace)
        nid = ua.NodeId("m/x", 1)
        objects = server.nodes.objects
        node = await objects.add_variable(nid, "x", 1.0)
        await server.start()
        try:
            client = Client(f"opc.tcp://127.0.0.1:{port}/", timeout=10)
            async with client:
                changes = Changes()
                sub = await client.create_subscription(20, changes)
                await sub.subscribe_data_change(client.get_node(nid))
                other = await client.create_subscription(20, Changes())
                handle = await other.subscribe_data_change(client.get_node(nid))
                await changes.until("m/x", 1.0, 10)
                assert await parking.park([nid]) == 2
                await changes.status("m/x", ua.StatusCodes.BadNodeIdUnknown, 10)
                await server.delete_nodes([node])
                await other.unsubscribe(handle)  # its client gave up meanwhile
                assert parking.items == 1
                await objects.add_variable(nid, "x", 2.0)
                assert parking.unpark([nid]) == 1
                await server.write_attribute_value(nid, ua.DataValue(ua.Variant(3.0)))
                await changes.until("m/x", 3.0, 10)
        finally:
            await server.stop()

    asyncio.run(body())
