"""Which replier is the machine's, against the scripted machine (tests/rider/scripted.py): a
replier allowed once is looked at again when the machine's holders change, and a replier or a
stand-in that a liveliness look does not name is looked for once more before it is refused
(moved from test_replies.py)."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import pytest
import zenoh

from ride_machine.rider.client import DuplicateMachine, Rider
from ride_machine.schema.codec import encode
from ride_machine.schema.commands import CommandRequest
from tests.procs import free_port, write_zenoh_config
from tests.rider.scripted import MSGPACK, Scripted, good_reply, rider_for


def test_a_replier_allowed_once_is_looked_at_again_when_the_holders_change(
    scripted: Scripted, tmp_path: Path
) -> None:
    with rider_for(scripted, tmp_path) as r:
        r.check_home()  # first contact: the scripted machine names no holder, its reply pins it
        known = r.transport.pins.known["m1"]
        pinned = known.pinned
        assert pinned is not None and known.allowed is not None
        for _ in range(3):
            r.check_home()  # the same replier: remembered, still allowed
        assert known.pinned == pinned
        # A holder token for another session appears (what `subscribe` hears): the same
        # replier is no longer the machine's, and its next reply is refused, not remembered.
        known.update("holder", "another-session", True)
        with pytest.raises(DuplicateMachine, match="this Rider talks to"):
            r.check_home()


@pytest.mark.hazard("H34")
def test_a_replier_no_look_names_is_looked_for_once_more_before_it_is_a_second_daemon(
    scripted: Scripted, tmp_path: Path
) -> None:
    """A liveliness query can come back short: the project's CI (stop 50) saw a Rider refuse
    the supervisor's `sim/world` reply as a second daemon's while that supervisor's token was
    up all along. A replier the look does not name is looked for once more, after a pause;
    named then (here: its supervisor token declared during the pause) it is the machine's; not
    named by either look, it is refused with what the looks saw."""
    session = scripted.session
    assert session is not None
    me = str(session.zid())
    holder = session.liveliness().declare_token("machine/m1/holder/the-daemon")
    supervisor = TokenAtFirstPause(session, f"machine/m1/supervisor/{me}")
    try:
        with rider_for(scripted, tmp_path) as r:
            supervisor.attach(r)
            assert r.check_home().ok  # the first look names the daemon only
            known = r.transport.pins.known["m1"]
            assert (known.pinned, known.supervisors) == ("the-daemon", {me})
            assert supervisor.pauses == [0.1]
            supervisor.withdraw()
            known.update("supervisor", me, False)  # what a liveliness subscriber hears
            with pytest.raises(DuplicateMachine) as refused:
                r.check_home()
            assert supervisor.pauses == [0.1, 0.1]  # looked for twice, then refused
            assert "holders seen: the-daemon; supervisors seen: none" in str(refused.value)
    finally:
        holder.undeclare()
        supervisor.close()


def test_a_stand_in_no_look_names_is_looked_for_once_more_before_two_repliers_are_refused(
    scripted: Scripted, tmp_path: Path
) -> None:
    """The daemon and its supervisor's stand-in both answer for a moment after a restart; the
    stand-in's reply is dropped when a look names it a supervisor. The project's CI (stop 51)
    saw a restarted daemon's status refused as a duplicate because the look missed the
    supervisor's token: a look that names no replier a supervisor is taken again, after a
    pause (here: the token declared during it); named by neither look, both are refused."""
    daemon = scripted.session
    assert daemon is not None
    stand_in_at = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([stand_in_at]))

    def stand_in_answer(query: zenoh.Query) -> None:
        with query:
            tid = msgpack.unpackb(query.payload.to_bytes())["transaction_id"]
            query.reply(query.key_expr, encode(good_reply(tid)), encoding=MSGPACK)

    with zenoh.open(conf) as stand_in:
        queryable = stand_in.declare_queryable("machine/m1/cmd/**", stand_in_answer)
        holder = daemon.liveliness().declare_token(f"machine/m1/holder/{daemon.zid()}")
        supervisor = TokenAtFirstPause(stand_in, f"machine/m1/supervisor/{stand_in.zid()}")
        try:
            conf_path = write_zenoh_config(tmp_path)
            with Rider(
                "m1", connect=[scripted.endpoint, stand_in_at], zenoh_config_path=conf_path
            ) as r:
                repliers_reached(r)  # two repliers, or the test says nothing
                supervisor.attach(r)
                assert r.check_home().ok  # the first look names no supervisor; the second does
                assert r.transport.pins.known["m1"].supervisors == {str(stand_in.zid())}
                assert supervisor.pauses == [0.1]
                supervisor.withdraw()
                with pytest.raises(DuplicateMachine, match="2 sessions replied"):
                    r.check_home()
                assert supervisor.pauses == [0.1, 0.1]  # looked for twice, then refused
        finally:
            holder.undeclare()
            queryable.undeclare()
            supervisor.close()


@dataclass
class TokenAtFirstPause:
    """The Rider's pause hook (`Pinning.pause`): each pause recorded; at the first, `session`
    declares the supervisor token `key` and waits until the Rider's session sees it."""

    session: zenoh.Session
    key: str
    rider: Rider | None = None
    pauses: list[float] = field(default_factory=list)
    token: zenoh.LivelinessToken | None = None

    def attach(self, rider: Rider) -> None:
        self.rider = rider
        rider.transport.pins.pause = self

    def __call__(self, seconds: float) -> None:
        self.pauses.append(seconds)
        if len(self.pauses) == 1 and self.rider is not None:
            self.token = self.session.liveliness().declare_token(self.key)
            token_seen(self.rider, self.key, True)

    def withdraw(self) -> None:
        """Undeclare the token and wait until the Rider's session no longer sees it."""
        self.close()
        if self.rider is not None:
            token_seen(self.rider, self.key, False)

    def close(self) -> None:
        if self.token is not None:
            self.token.undeclare()
            self.token = None


def token_seen(r: Rider, key: str, up: bool) -> None:
    """Wait (bounded) until the Rider's session sees the liveliness token `key` `up` (a loaded
    host delivers a declaration or an undeclaration late)."""
    deadline = time.monotonic() + 10.0
    while bool([t for t in r.transport.link.session.liveliness().get(key) if t.ok]) != up:
        assert time.monotonic() < deadline, f"the token never reached the Rider ({up})"


def repliers_reached(r: Rider) -> None:
    """Wait (bounded) until a plain query from the Rider's session gets two replies."""
    request = encode(CommandRequest(transaction_id="probe-1"))
    deadline = time.monotonic() + 10.0
    while True:
        replies = r.transport.link.session.get(
            "machine/m1/cmd/check/home",
            payload=request,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=2.0,
        )
        if len([x for x in replies if x.ok]) >= 2:
            return
        assert time.monotonic() < deadline, "both repliers never answered"
        time.sleep(0.05)
