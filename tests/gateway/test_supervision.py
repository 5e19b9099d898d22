"""A motion started through OPC UA is supervised like a Rider's: its client closing its session
without Stop, or freezing, pauses the machine (within session timeout + rider-loss timeout)."""

from __future__ import annotations

import json
import signal
import time

import pytest
from asyncua import ua

from ride_machine.schema.status import MachineState
from tests.gateway.support import SESSION_TIMEOUT_S, Credentials, GatewayProc, python_client, until
from tests.gateway.ua import call, connected, run
from tests.integration.support import prepare
from tests.site.stand import Site

pytestmark = pytest.mark.integration

RIDER_LOSS_S = 1.0
"""`rider_loss.timeout_s` of the fast config the plant's daemons run (tests/integration)."""
LONG = json.dumps(
    {"name": "long", "steps": [{"kind": "rotate", "direction": "cw", "revolutions": 200}]}
)
"""A session that runs far longer than any of these tests (0.5 s a revolution)."""

CLIENT = """
import asyncio, sys
from asyncua import Client, ua
async def main(url, password, session):
    c = Client(url, timeout=10)
    c.set_user("operator"); c.set_password(password)
    await c.connect()
    idx = await c.get_namespace_index("urn:ride-machine:gateway")
    req = ua.CallMethodRequest(ObjectId=ua.NodeId("m1", idx), MethodId=ua.NodeId("m1/Start", idx),
                               InputArguments=[ua.Variant(session, ua.VariantType.String)])
    (res,) = await c.uaclient.call([req])
    print("started", res.OutputArguments[0].Value, flush=True)
    await asyncio.sleep(3600)
asyncio.run(main(*sys.argv[1:]))
"""


def _state(plant: Site) -> MachineState:
    with plant.rider("m1", timeout=5.0, supervise=False) as r:
        return r.status().state


def _silent_for(gateway: GatewayProc) -> float:
    """How long the next supervising session the gateway ended for silence had been silent."""
    while True:
        _, line = gateway.lines.wait_for("event=opcua_rider_ended")
        idle = float(line.rsplit("idle_s=", 1)[1].split()[0])
        if idle >= 1.0:  # not a session closed at once (the test before)
            return idle


def _ready(plant: Site) -> None:
    """Calibrated, home, at rest: a Start is accepted."""
    with plant.rider("m1", timeout=5.0) as r:
        r.stop()
        prepare(r)


@pytest.mark.hazard("H53")
def test_a_session_closed_without_stop_pauses_its_motion(
    plant: Site, gateway: GatewayProc, creds: Credentials
) -> None:
    _ready(plant)

    async def start_and_leave() -> None:
        async with connected(gateway.url, "operator", creds.password) as c:
            got = await call(c, "m1", "Start", ua.Variant(LONG, ua.VariantType.String))
            assert got.code == "RESP_START_ACCEPTED", got

    run(start_and_leave())
    left = time.monotonic()
    until("PAUSED", lambda: _state(plant) is MachineState.PAUSED or None)
    # Closing the session drops its Rider's token: the policy acts at once (no timeout).
    assert time.monotonic() - left < RIDER_LOSS_S + SESSION_TIMEOUT_S + 5
    with plant.rider("m1", timeout=5.0) as r:
        events = r.events(kinds=("rider_lost",), last=1)
    assert events and events[-1].details.acted  # type: ignore[union-attr]


@pytest.mark.hazard("H53")
def test_a_frozen_client_pauses_its_motion_within_the_two_timeouts(
    plant: Site, gateway: GatewayProc, creds: Credentials
) -> None:
    _ready(plant)
    child = python_client(CLIENT, gateway.url, creds.password, LONG)
    try:
        assert child.stdout is not None
        line = child.stdout.readline()
        assert line.split() == ["started", "RESP_START_ACCEPTED"], (line, child.stderr)
        # A client that is there but idle keeps its session (its keep-alive) and its motion:
        # nothing may pause it over a few session timeouts (the span is what is asserted).
        time.sleep(2 * SESSION_TIMEOUT_S)
        assert _state(plant) is MachineState.RUNNING
        child.send_signal(signal.SIGSTOP)  # its link frozen: the TCP connection stays open
        frozen = time.monotonic()
        until("PAUSED", lambda: _state(plant) is MachineState.PAUSED or None, timeout=30)
        took = time.monotonic() - frozen
        # The documented bound (session timeout + rider-loss timeout + one check), counted
        # from the client's last request (at most one keep-alive before the freeze), and the
        # slack a loaded host needs.
        assert took < SESSION_TIMEOUT_S + RIDER_LOSS_S + 5, took
        # Ended because its session went silent for the session timeout (not sooner).
        assert _silent_for(gateway) >= SESSION_TIMEOUT_S
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        with plant.rider("m1", timeout=5.0) as r:
            r.stop()
