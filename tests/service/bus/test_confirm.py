"""A command that names a Rider waits while that Rider is asked whether it sent it
(service/bus/confirm.py), and a Stop never waits behind it.

Real Zenoh sessions (the test's "Rider" answers on `rider/<login>/<zid>/confirm` with a
queryable of its own); the machine is the simulator rig with a fake clock.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator

import msgpack
import pytest
import zenoh

from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import CommandEvent
from ride_machine.schema.rider import CONFIRMED, DENIED, confirm_key, digest
from ride_machine.service.bus.commands import Commands
from ride_machine.service.bus.confirm import Confirmer, Verdict
from ride_machine.service.bus.routes import declare
from ride_machine.service.core.history.events import ListEventSink
from ride_machine.service.core.scan.port import LoopPort
from tests.rig import Rig
from tests.service.bus.test_bus_commands import BASE, reply_of, until
from tests.service.bus.test_bus_routes import Host

TIMEOUT_S = 5.0
"""Long enough for a loaded host: a Rider that answers ends the wait at once."""
SILENT_S = 0.3
"""The wait for a Rider that is not there."""


def rider_of(session: zenoh.Session) -> str:
    """The Rider id a queryable of `session` may answer for (the machine checks the replier)."""
    return f"bay1/{session.zid()}"


@pytest.fixture
def machine(session: zenoh.Session) -> Iterator[tuple[Rig, Commands, ListEventSink]]:
    sink = ListEventSink()
    rig = Rig(events=sink)
    bus = Commands(BASE, LoopPort(rig.loop, rig.clock), Confirmer(session, TIMEOUT_S))
    declared = declare(session, BASE, Host(), bus.routes())
    yield rig, bus, sink
    for entity in declared:
        entity.undeclare()


class FakeRider:
    """Answers confirmation queries for `rider_of(session)`: the digests it was told it sent;
    held back until `release` when `hold` is set."""

    def __init__(self, session: zenoh.Session, hold: bool = False) -> None:
        self.id = rider_of(session)
        self.sent: set[bytes] = set()
        self.asked = threading.Event()
        self.release = threading.Event()
        if not hold:
            self.release.set()
        self._queryable = session.declare_queryable(confirm_key(self.id), self._answer)

    def _answer(self, query: zenoh.Query) -> None:
        self.asked.set()
        self.release.wait(5.0)
        payload = query.payload
        said = CONFIRMED if payload is not None and payload.to_bytes() in self.sent else DENIED
        with query:
            query.reply(query.key_expr, said)

    def close(self) -> None:
        self._queryable.undeclare()


def body(tid: str, rider: str | None) -> bytes:
    return msgpack.packb({"transaction_id": tid, "rider": rider})


def send(session: zenoh.Session, key: str, payload: bytes) -> zenoh.handlers.Handler[zenoh.Reply]:
    return session.get(f"{BASE}/cmd/{key}", payload=payload, timeout=5.0)


def recorded(sink: ListEventSink, rig: Rig) -> dict[str | None, CommandEvent]:
    rig.loop.recorder.release()
    return {d.transaction_id: d for d, _, _ in sink.events if isinstance(d, CommandEvent)}


def test_a_command_its_rider_confirmed_runs_and_is_recorded_as_that_rider(
    session: zenoh.Session, machine: tuple[Rig, Commands, ListEventSink]
) -> None:
    rig, _, sink = machine
    rider = FakeRider(session)
    try:
        payload = body("home-1", rider.id)
        rider.sent.add(digest(payload))
        reply = reply_of(send(session, "home", payload))
    finally:
        rider.close()
    assert reply.error is None or reply.error.code is not ErrorCode.RIDER_UNCONFIRMED, reply
    assert rider.asked.is_set()
    event = recorded(sink, rig)["home-1"]
    assert event.rider == rider.id and event.identity == rider.id


@pytest.mark.hazard("H54")
@pytest.mark.parametrize("answers", [True, False], ids=["denied", "silent"])
def test_a_motion_command_its_rider_does_not_confirm_is_refused_and_recorded(
    session: zenoh.Session, machine: tuple[Rig, Commands, ListEventSink], answers: bool
) -> None:
    rig, bus, sink = machine
    events: list[object] = []
    cycles: list[int | None] = []

    def emit_now(details: object, cycle: int | None = None) -> None:
        events.append(details)
        cycles.append(cycle)

    bus.events = type("Log", (), {"emit_now": staticmethod(emit_now)})()  # type: ignore[assignment]
    rider = FakeRider(session) if answers else None  # it never sent it / no such Rider
    if not answers:
        bus.confirmer = Confirmer(session, SILENT_S)
    try:
        reply = reply_of(send(session, "start", body("forged-1", rider_of(session))))
    finally:
        if rider is not None:
            rider.close()
    assert reply.error is not None and reply.error.code is ErrorCode.RIDER_UNCONFIRMED, reply
    assert ("did not send" if answers else "did not confirm") in reply.error.message
    assert reply.error.path == "/rider"
    assert "forged-1" not in recorded(sink, rig)  # never reached the loop: nothing bound
    [event] = events
    assert isinstance(event, CommandEvent) and event.identity is None
    assert event.rider == rider_of(session) and event.code == "RIDER_UNCONFIRMED"
    assert cycles == [rig.loop.cycle]  # among the events of the cycle it was refused in


def test_a_command_that_names_no_rider_is_not_asked_about(
    session: zenoh.Session, machine: tuple[Rig, Commands, ListEventSink]
) -> None:
    rig, _, sink = machine
    reply = reply_of(send(session, "home", body("anonymous-1", rider=None)))
    assert reply.error is None or reply.error.code is not ErrorCode.RIDER_UNCONFIRMED, reply
    assert recorded(sink, rig)["anonymous-1"].identity is None


@pytest.mark.hazard("H54")
def test_a_stop_never_waits_for_a_confirmation_and_the_start_it_overtook_is_refused(
    session: zenoh.Session, machine: tuple[Rig, Commands, ListEventSink]
) -> None:
    """The operator presses Start, then Stop, while the machine asks the Start's Rider: the
    Stop is answered at once, and the Start, confirmed later, does not move the machine."""
    rig, bus, sink = machine
    rider = FakeRider(session, hold=True)
    try:
        start = body("start-then-stop", rider.id)
        rider.sent.add(digest(start))
        pending = send(session, "start", start)
        assert rider.asked.wait(5.0)
        stop = reply_of(send(session, "stop", body("the-stop", rider.id)))
        assert bus.deferred.pending == 1  # the Start is still waiting for its Rider
        rider.release.set()
        refused = reply_of(pending)
    finally:
        rider.release.set()
        rider.close()
    assert stop.transaction_id == "the-stop" and stop.error is None, stop
    assert refused.error is not None and refused.error.code is ErrorCode.SUPERSEDED, refused
    until(lambda: bus.deferred.pending == 0)
    assert list(recorded(sink, rig)) == ["the-stop"]


def test_an_id_without_a_login_is_nobody_to_ask(session: zenoh.Session) -> None:
    assert Confirmer(session, TIMEOUT_S).ask("0123abcd", b"{}").verdict is Verdict.UNNAMED
