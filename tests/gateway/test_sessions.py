"""The gateway reads asyncua's session registry (it has no public listing): pinned here against
a real asyncua server, so an asyncua release that moves it fails this test, not a ride."""

from __future__ import annotations

import asyncio

from asyncua import Client, Server, ua

from rider.gateway.security import Rules, Users
from rider.gateway.supervision import open_session_keys
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
