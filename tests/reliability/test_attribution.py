"""Who asked is proven, not claimed (issue 58, reproduction 2): station `bay2` copies station
`bay1`'s Rider id (read from the history) into a Start and a parameter write of its own.

On the old main the Start was accepted, recorded `from bay1/<zid>`, and the ride was bound to
bay1's live session: bay1's operator became the deadman of a ride they did not start. Now the
machine asks the Rider a request names, on `rider/<login>/<zid>/confirm`, before it binds a ride
or records a sender: bay1's Rider never sent it and says so, and bay2 cannot answer in bay1's
place (the ACL drops its queryable there). A real daemon (and its supervisor), real sessions.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from ride_machine.common.credentials import RIDER
from ride_machine.rider.client import Rider
from ride_machine.rider.link import zenoh_config
from ride_machine.schema.codec import Format, decode, encode
from ride_machine.schema.commands import Reply, StartRequest
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import CommandEvent, EventQuery, ParamEvent
from ride_machine.schema.params import ParamSet, ParamValue
from ride_machine.schema.rider import CONFIRMED, confirm_key
from ride_machine.schema.status import MachineState
from tests.integration.support import prepare
from tests.procs import Daemon
from tests.reliability.support import RIDER_VARIABLES, Identities, environ, rider_as
from tests.reliability.support import secured_machine as start_secured
from tests.reliability.test_stations import stations  # noqa: F401 - the module's fixture

pytestmark = pytest.mark.integration

PARAM = "bus.heartbeat_s"
"""A setting that is no safety setting: the write is taken, only its record is in question."""


@contextlib.contextmanager
def raw_session(daemon: Daemon, env: dict[str, str]) -> Iterator[zenoh.Session]:
    """A plain Zenoh session logged in with `env`'s credentials: no Rider library, so it sends
    exactly what the test writes (attachment included)."""
    with environ({**dict.fromkeys(RIDER_VARIABLES), **env}):
        conf = zenoh_config(daemon.zenoh_config, [daemon.endpoint])
    session = zenoh.open(conf)
    try:
        yield session
    finally:
        session.close()


def ask(session: zenoh.Session, key: str, payload: bytes, claimed: str) -> list[zenoh.Reply]:
    """One query that claims to come from Rider `claimed`, retried while no queryable matched
    yet (the session was just opened)."""
    deadline = time.monotonic() + 10.0
    while True:
        attachment = f"rider={claimed}".encode()
        replies = list(session.get(key, payload=payload, attachment=attachment, timeout=5.0))
        if replies or time.monotonic() > deadline:
            return replies
        time.sleep(0.05)


def only(replies: list[zenoh.Reply]) -> bytes:
    [reply] = replies
    sample = reply.ok if reply.ok is not None else reply.err
    assert sample is not None
    return sample.payload.to_bytes()


def events_of(rider: Rider, kind: str) -> list[object]:
    return [e.details for e in rider.events(EventQuery(kinds=(kind,)))]


def forge(daemon: Daemon, env: dict[str, str], victim: str) -> tuple[Reply, ParamValue]:
    """A Start and a parameter write from a session logged in with `env`, both naming Rider
    `victim` (its `rider` field and attachment), while it answers yes in `victim`'s place."""
    base = f"machine/{daemon.machine_id}"
    with raw_session(daemon, env) as bay2:
        # bay2 also answers in bay1's place: the ACL drops its declaration there.
        def yes(query: zenoh.Query) -> None:
            with query:
                query.reply(query.key_expr, CONFIRMED)

        fake = bay2.declare_queryable(confirm_key(victim), yes)
        start = StartRequest(
            transaction_id="bay2-forged-start",
            timecode=time.time(),
            valid_for=10.0,
            rider=victim,
        )
        forged = decode(
            Reply,
            only(ask(bay2, f"{base}/cmd/start", encode(start), victim)),
            Format.MSGPACK,
        )
        write = ParamSet(transaction_id="bay2-forged-param", value=0.9)
        taken = decode(
            ParamValue,
            only(ask(bay2, f"{base}/params/{PARAM}", encode(write), victim)),
            Format.MSGPACK,
        )
        fake.undeclare()
    return forged, taken


@pytest.mark.hazard("H54")
@pytest.mark.parametrize("command", ["run", "supervise"])
def test_a_station_claiming_anothers_id_neither_binds_a_ride_nor_is_recorded_as_it(
    tmp_path_factory: pytest.TempPathFactory,
    stations: tuple[Identities, Path],  # noqa: F811 - the fixture imported above
    command: str,
) -> None:
    ids, profile = stations
    tmp = tmp_path_factory.mktemp(f"attribution-{command}")
    daemon, _ = start_secured(tmp, ids, command, profile, "bay1")
    try:
        with rider_as(daemon, ids.env(RIDER, "bay1"), timeout=5.0) as bay1:
            prepare(bay1)
            victim = bay1.rider_id
            forged, taken = forge(daemon, ids.env(RIDER, "bay2"), victim)
            assert not forged.success and forged.error is not None, forged
            assert forged.error.code is ErrorCode.RIDER_UNCONFIRMED, forged.error
            assert "did not send" in forged.error.message, forged.error.message
            assert bay1.status().state is MachineState.IDLE  # nothing moved, nothing bound
            assert taken.value == 0.9  # a write is taken: only its record is in question

            own = bay1.start()  # bay1's own Start is confirmed and bound to bay1
            assert own.success, own
            assert bay1.status().rider_connected
            bay1.stop()
            bay1.set_param(PARAM, 1.0)

            commands = {
                d.transaction_id: d
                for d in events_of(bay1, "command")
                if isinstance(d, CommandEvent)
            }
            params = [d for d in events_of(bay1, "param_changed") if isinstance(d, ParamEvent)]
        record = commands["bay2-forged-start"]
        assert record.rider == victim and record.identity is None, record
        assert not record.accepted and record.code == "RIDER_UNCONFIRMED", record
        assert commands[own.transaction_id].identity == victim
        claimed = [p for p in params if p.transaction_id == "bay2-forged-param"]
        assert claimed and claimed[0].by == victim and claimed[0].identity is None, params
        confirmed = [p for p in params if p.new == 1.0]
        assert confirmed and confirmed[0].identity == victim, params
    finally:
        daemon.stop()
