"""The gateway under the ACL profile (zenoh/acl.json5): logged in as `monitor` it reads and
refuses every call (`--monitor`); logged in as `rider` it commands and supervises."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from asyncua import Client, ua

from ride_machine.common.credentials import MACHINE, RIDER, env_name
from tests.gateway.support import Credentials, running_gateway
from tests.gateway.ua import call, connected, eventually, read, run
from tests.procs import Daemon, rider_cmd
from tests.reliability.support import ACL_PROFILE, Identities, make_identities, start_machine

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Daemon, Identities]]:
    tmp = tmp_path_factory.mktemp("acl-gateway")
    ids = make_identities(tmp / "secrets")
    daemon = start_machine(
        tmp,
        profile=ACL_PROFILE,
        env={env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary)},
        rider_env=ids.env(RIDER, "rider"),
    )
    try:
        yield daemon, ids
    finally:
        daemon.stop()


def _rider(daemon: Daemon) -> list[str]:
    return rider_cmd("--connect", daemon.endpoint, "--zenoh-config", str(daemon.zenoh_config))


@pytest.mark.hazard("H52")
def test_a_monitor_gateway_reads_and_refuses_every_call(
    secured: tuple[Daemon, Identities], creds: Credentials
) -> None:
    daemon, ids = secured
    env = ids.env(RIDER, "monitor")
    with running_gateway(_rider(daemon), creds, "--monitor", env=env) as gw:

        async def body() -> None:
            async with connected(gw.url, "operator", creds.password) as c:
                state = await _good(c, "State")
                home = await call(c, "m1", "Home")
                assert home.status.value == ua.StatusCodes.BadUserAccessDenied, home
                assert home.code == "READ_ONLY"
                assert (await read(c, "m1", "State")).Value.Value == state

        run(body())


def test_a_rider_gateway_commands_under_the_acl(
    secured: tuple[Daemon, Identities], creds: Credentials
) -> None:
    daemon, ids = secured
    with running_gateway(_rider(daemon), creds, env=ids.env(RIDER, "rider")) as gw:

        async def body() -> None:
            async with connected(gw.url, "operator", creds.password) as c:
                await _good(c, "State")
                stop = await call(c, "m1", "Stop")
                assert stop.good and stop.code == "RESP_DONE", stop

        run(body())


async def _good(client: Client, path: str) -> str:
    async def value() -> str | None:
        dv = await read(client, "m1", path)
        return str(dv.Value.Value) if dv.StatusCode.is_good() else None

    return await eventually(f"m1/{path} readable", value)
