"""The bus's route table: one Request per query, the one wildcard rule, the one refusal shape.

A real Zenoh session (no network: it queries its own queryables) answers through `declare`, so
these tests pin what a caller receives, without a daemon.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import cast

import pytest
import zenoh
from pydantic import BaseModel

from ride_machine.schema.codec import MAX_PAYLOAD_BYTES, Format, decode
from ride_machine.schema.commands import Reply
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.sim import SimEstop, SimWorldState
from ride_machine.schema.status import MachineState
from ride_machine.service.bus.commands import command_route
from ride_machine.service.bus.injection import Injection
from ride_machine.service.bus.request import Request, sender_of
from ride_machine.service.bus.routes import (
    PUT_LOG_S,
    PutWarner,
    Route,
    Wildcard,
    declare,
)
from ride_machine.service.bus.supervisor import SupervisorBus
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.errors import Busy, MachineError, UnknownCommand

BASE = "machine/t1"
WALL = 1234.5


class Host:
    def wall(self) -> float:
        return WALL

    def state(self) -> MachineState | None:
        return MachineState.IDLE


@dataclass
class Answer:
    ok: bool
    key: str
    data: bytes

    def reply(self) -> Reply:
        return decode(Reply, self.data, Format.JSON)


def ask(session: zenoh.Session, key: str, payload: bytes | None = None) -> list[Answer]:
    answers = []
    selector = f"{key}?format=json"
    for r in session.get(selector, payload=payload, timeout=2.0):
        sample = r.ok if r.ok is not None else r.err
        assert sample is not None
        key_of = str(r.ok.key_expr) if r.ok is not None else ""
        answers.append(Answer(r.ok is not None, key_of, sample.payload.to_bytes()))
    return answers


class Echo(BaseModel):
    key: str


@dataclass
class Calls:
    seen: list[str] = field(default_factory=list)

    def ok(self, request: Request) -> None:
        self.seen.append(request.key)
        request.reply(Echo(key=request.key))

    def busy(self, request: Request) -> None:
        self.seen.append(request.key)
        raise Busy("queue full")


@pytest.fixture
def routes(session: zenoh.Session) -> Iterator[Calls]:
    calls = Calls()
    table = [
        Route("read/**", calls.ok),
        Route("act/**", calls.ok, Wildcard.REFUSE, what="an act", example="act/x"),
        Route("busy", calls.busy, Wildcard.REFUSE, sniff=True, what="busy", example="busy"),
        Route("params/**", calls.ok, Wildcard.REFUSE_WRITES, what="a write", example="params/x"),
        command_route(calls.ok),
    ]
    entities = declare(session, BASE, Host(), table)
    yield calls
    for entity in entities:
        entity.undeclare()


def test_a_raised_machine_error_is_one_reply_in_the_refusal_shape(
    session: zenoh.Session, routes: Calls
) -> None:
    (answer,) = ask(session, f"{BASE}/busy", b'{"transaction_id": "t-1"}')
    assert answer.ok and answer.key == f"{BASE}/busy"
    reply = answer.reply()
    assert not reply.success and reply.error is not None
    assert (reply.error.code, reply.error.message) == (ErrorCode.BUSY, "queue full")
    assert (reply.transaction_id, reply.state, reply.timecode) == ("t-1", MachineState.IDLE, WALL)
    assert reply.error_message == "queue full"


@pytest.mark.parametrize(
    ("parameters", "fmt"),
    [
        ("", Format.MSGPACK),
        ("?format=json", Format.JSON),
        ("?x=1;format=JSON", Format.JSON),
        ("?format=msgpack", Format.MSGPACK),
        ("?formats=json", Format.MSGPACK),
    ],
)
def test_the_reply_format_comes_from_the_selector_and_the_key_goes_without_it(
    session: zenoh.Session, routes: Calls, parameters: str, fmt: Format
) -> None:
    (reply,) = session.get(f"{BASE}/read/a{parameters}", timeout=2.0)
    assert reply.ok is not None
    assert str(reply.ok.key_expr) == f"{BASE}/read/a"
    assert decode(Echo, reply.ok.payload.to_bytes(), fmt) == Echo(key=f"{BASE}/read/a")
    assert str(reply.ok.encoding).startswith(fmt.value)
    assert routes.seen == [f"{BASE}/read/a"]


@pytest.mark.hazard("H31")
def test_a_wildcard_on_a_key_that_acts_is_refused_before_its_handler(
    session: zenoh.Session, routes: Calls
) -> None:
    (answer,) = ask(session, f"{BASE}/act/*", b'{"transaction_id": "t-2"}')
    reply = answer.reply()
    assert answer.ok and reply.error is not None and reply.error.code is ErrorCode.BAD_KEY
    assert reply.error.message == (
        f"wildcards are not allowed in an act: '{BASE}/act/*'; name one key of one machine,"
        f" e.g. {BASE}/act/x"
    )
    assert reply.transaction_id == "t-2"
    assert routes.seen == []
    assert [a.key for a in ask(session, f"{BASE}/act/x")] == [f"{BASE}/act/x"]


def test_a_wildcard_command_is_refused_as_a_zenoh_error_reply(
    session: zenoh.Session, routes: Calls
) -> None:
    (answer,) = ask(session, f"{BASE}/cmd/*", b'{"transaction_id": "t-3"}')
    assert not answer.ok  # the documented shape (docs/zenoh-cli.md)
    reply = answer.reply()
    assert reply.error is not None and reply.error.code is ErrorCode.BAD_KEY
    assert f"a command key: '{BASE}/cmd/*'; name one command of one machine" in reply.error.message
    assert reply.transaction_id == "t-3" and routes.seen == []


def test_a_named_wildcard_is_refused_and_a_broad_read_gets_nothing(
    session: zenoh.Session,
) -> None:
    calls = Calls()
    base = "machine/t3"
    route = Route("diag/reset", calls.ok, Wildcard.REFUSE_NAMED, what="a reset", example="x")
    entities = declare(session, base, Host(), [route])  # its queryable, its put warner
    try:
        (refused,) = ask(session, "machine/*/diag/reset")
        error = refused.reply().error
        assert refused.ok and error is not None and error.code is ErrorCode.BAD_KEY
        assert ask(session, f"{base}/diag/**") == []  # covers the key, does not name it
        assert calls.seen == []
        assert [a.key for a in ask(session, f"{base}/diag/reset")] == [f"{base}/diag/reset"]
    finally:
        for entity in entities:
            entity.undeclare()


def test_a_wildcard_read_is_answered_and_a_wildcard_write_refused(
    session: zenoh.Session, routes: Calls
) -> None:
    (read,) = ask(session, f"{BASE}/params/**")
    assert read.ok and json.loads(read.data) == {"key": f"{BASE}/params/**"}
    (write,) = ask(session, f"{BASE}/params/*", b'{"transaction_id": "w", "value": 1}')
    assert write.reply().error is not None
    assert write.reply().error.code is ErrorCode.BAD_KEY  # type: ignore[union-attr]
    assert routes.seen == [f"{BASE}/params/**"]


def test_an_unreadable_payload_names_its_problem(session: zenoh.Session) -> None:
    def decodes(request: Request) -> None:
        request.decode(SimEstop)
        raise UnknownCommand("not reached")

    (entity,) = declare(session, BASE, Host(), [Route("decode", decodes, sniff=True)])
    try:
        (answer,) = ask(session, f"{BASE}/decode", b'{"pressed": "maybe"}')
    finally:
        entity.undeclare()
    reply = answer.reply()
    assert reply.error is not None and reply.error.code is ErrorCode.BAD_PAYLOAD
    assert reply.error.path == "/pressed"


@pytest.mark.hazard("H30")
def test_a_payload_past_the_limit_is_told_by_its_length_and_never_copied(
    session: zenoh.Session,
) -> None:
    """A write refuses it; a read, which takes no payload, answers all the same."""
    seen: list[tuple[int, bytes]] = []

    def writes(request: Request) -> None:
        seen.append((request.size, request.body))
        request.decode(SimEstop)
        raise UnknownCommand("not reached")

    def reads(request: Request) -> None:
        seen.append((request.size, request.body))
        request.reply(Echo(key=request.key))

    size = MAX_PAYLOAD_BYTES + 1
    table = [Route("write", writes, sniff=True), Route("read", reads)]
    entities = declare(session, BASE, Host(), table)
    try:
        (refused,) = ask(session, f"{BASE}/write", b"{" + b" " * (size - 2) + b"}")
        (read,) = ask(session, f"{BASE}/read", b"x" * size)
    finally:
        for entity in entities:
            entity.undeclare()
    error = refused.reply().error
    assert error is not None and error.code is ErrorCode.PAYLOAD_TOO_LARGE
    assert error.message == f"payload is {size} bytes, the limit is {MAX_PAYLOAD_BYTES}"
    assert read.ok and json.loads(read.data) == {"key": f"{BASE}/read"}
    assert seen == [(size, b""), (size, b"")]  # its length only: nothing copied out of Zenoh


class Attachment:
    """An attachment that counts its copies (`to_bytes`), as Zenoh's `ZBytes` would make them."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.copies = 0

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        self.copies += 1
        return self.data


def test_an_attachment_no_rider_id_fits_in_is_not_copied() -> None:
    rider = b"rider=" + b"l" * 64 + b"/" + b"a" * 32  # the longest a Rider sends
    fits, huge = Attachment(rider), Attachment(b"rider=bay1/" + b"a" * (1 << 20))
    assert sender_of(SimpleNamespace(attachment=fits)) == rider[6:].decode()  # type: ignore[arg-type]
    assert sender_of(SimpleNamespace(attachment=huge)) is None  # type: ignore[arg-type]
    assert (fits.copies, huge.copies) == (1, 0)


class Failures(logging.Handler):
    """The bus's `event=handler_failed` lines, logged on Zenoh's thread after the reply left."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []
        self.arrived = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if "event=handler_failed" in record.getMessage():
            self.records.append(record)
            self.arrived.set()


@pytest.fixture
def failures() -> Iterator[Failures]:
    handler, logger = Failures(), logging.getLogger("ride_machine.service.bus.routes")
    logger.addHandler(handler)
    yield handler
    logger.removeHandler(handler)


@pytest.mark.hazard("H30")
def test_a_handler_that_fails_unexpectedly_still_gets_exactly_one_reply(
    session: zenoh.Session, failures: Failures
) -> None:
    def broken(request: Request) -> None:
        raise ValueError("a bug")

    (entity,) = declare(session, BASE, Host(), [Route("broken", broken)])
    try:
        answers = ask(session, f"{BASE}/broken", b'{"transaction_id": "t-9"}')
    finally:
        entity.undeclare()
    (answer,) = answers
    reply = answer.reply()
    assert answer.ok and not reply.success and reply.error is not None
    assert reply.error.code is ErrorCode.INTERNAL and "ValueError" in reply.error.message
    assert (reply.transaction_id, reply.state) == ("t-9", MachineState.IDLE)
    assert failures.arrived.wait(5.0)
    [logged] = failures.records
    assert f"key={BASE}/broken error=ValueError refused=True" in logged.getMessage()
    assert logged.exc_info is not None  # the traceback, once


def test_a_handler_that_fails_after_its_reply_leaves_that_reply_the_only_one(
    session: zenoh.Session, failures: Failures
) -> None:
    def replies_then_fails(request: Request) -> None:
        request.reply(Echo(key=request.key))
        raise ValueError("a bug after the reply")

    (entity,) = declare(session, BASE, Host(), [Route("late", replies_then_fails)])
    try:
        (answer,) = ask(session, f"{BASE}/late")
    finally:
        entity.undeclare()
    assert answer.ok and json.loads(answer.data) == {"key": f"{BASE}/late"}
    assert failures.arrived.wait(5.0)
    [logged] = failures.records
    assert "error=ValueError refused=False" in logged.getMessage()


@dataclass
class FakeWorld:
    """A `SimPort` that records what it was asked to inject."""

    applied: list[BaseModel] = field(default_factory=list)

    def decode(self, what: str, payload: bytes, encoding: str | None) -> BaseModel:
        if what != "estop":
            raise UnknownCommand(f"unknown sim key {what!r}")
        return SimEstop.model_validate_json(payload or b"{}")

    def apply(self, request: BaseModel) -> None:
        self.applied.append(request)

    def world(self, stamp: float) -> SimWorldState:
        pressed = bool(self.applied) and getattr(self.applied[-1], "pressed", False)
        return SimWorldState(
            time=stamp,
            tilt_deg=0.0,
            rotate_deg=0.0,
            revolutions=0.0,
            estop_pressed=pressed,
            relays={},
            faults={},
        )


def test_the_sim_route_injects_reads_and_refuses_without_a_simulator(
    session: zenoh.Session,
) -> None:
    world = FakeWorld()
    ran: list[str] = []

    def run(request: Request, make: Callable[[], BaseModel]) -> None:  # `Runner`: make, reply
        ran.append(request.key)
        request.reply(make())

    with_sim = Injection(BASE, world, "sim", run, lambda: WALL)
    without = Injection("machine/t2", None, "revpi", run, lambda: WALL)
    entities = declare(session, BASE, Host(), with_sim.routes())
    entities += declare(session, "machine/t2", Host(), without.routes())
    try:
        (pressed,) = ask(session, f"{BASE}/sim/estop", b'{"pressed": true}')
        assert decode(SimWorldState, pressed.data, Format.JSON).estop_pressed
        assert ran == [f"{BASE}/sim/estop"]  # the fault went through the runner
        (state,) = ask(session, f"{BASE}/sim/world")
        assert decode(SimWorldState, state.data, Format.JSON).time == WALL
        (unknown,) = ask(session, f"{BASE}/sim/fly")
        assert unknown.reply().error.code is ErrorCode.UNKNOWN_COMMAND  # type: ignore[union-attr]
        (none,) = ask(session, "machine/t2/sim/estop", b'{"pressed": true}')
        error = none.reply().error
        assert error is not None and error.code is ErrorCode.NOT_AVAILABLE
        assert "runs the revpi HAL, not the simulator" in error.message
    finally:
        for entity in entities:
            entity.undeclare()
    assert len(world.applied) == 1


def test_the_supervisor_refuses_a_wildcard_injection(session: zenoh.Session) -> None:
    world = FakeWorld()
    config = MachineConfig.model_validate({"machine": {"id": "sup1"}})
    bus = SupervisorBus(session, config, world=world, on_presence=lambda up: None)
    bus.start()
    try:
        answers = ask(session, "machine/*/sim/estop", b'{"pressed": true}')
        assert answers and all(not a.reply().success for a in answers)
        assert {a.reply().error.code for a in answers} == {ErrorCode.BAD_KEY}  # type: ignore[union-attr]
        (pressed,) = ask(session, "machine/sup1/sim/estop", b'{"pressed": true}')
        assert decode(SimWorldState, pressed.data, Format.JSON).estop_pressed
    finally:
        bus.close()
    assert len(world.applied) == 1  # the wildcard pressed nothing


def test_every_refusal_is_a_machine_error_with_a_wire_code() -> None:
    from ride_machine.service import errors

    classes = [
        c
        for c in vars(errors).values()
        if isinstance(c, type) and issubclass(c, MachineError) and c is not MachineError
    ]
    assert classes and all(isinstance(c.code, ErrorCode) for c in classes)


class _Put:
    """What `PutWarner` reads of a `zenoh.Sample`."""

    def __init__(self, key_expr: str, kind: zenoh.SampleKind = zenoh.SampleKind.PUT) -> None:
        self.key_expr, self.kind = key_expr, kind


def test_a_peer_putting_in_a_loop_gets_a_line_a_second_with_the_count(
    caplog: pytest.LogCaptureFixture,
) -> None:
    now = [0.0]
    warner = PutWarner(clock=lambda: now[0])
    put = cast(Callable[[_Put], None], warner.sample)
    with caplog.at_level(logging.WARNING, logger="ride_machine.service.bus.routes"):
        put(_Put(f"{BASE}/cmd/home"))
        for _ in range(999):  # within the second: counted, not logged
            now[0] += 0.0005
            put(_Put(f"{BASE}/cmd/home"))
        now[0] = PUT_LOG_S + 0.001
        put(_Put(f"{BASE}/cmd/stop", zenoh.SampleKind.DELETE))
        now[0] += PUT_LOG_S
        put(_Put(f"{BASE}/sim/estop"))
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3, lines
    assert f"key='{BASE}/cmd/home' kind=put unlogged=0" in lines[0]
    assert "answers queries, not puts" in lines[0] and "zenoh get -s" in lines[0]
    assert f"key='{BASE}/cmd/stop' kind=delete unlogged=999" in lines[1]
    assert f"key='{BASE}/sim/estop' kind=put unlogged=0" in lines[2]
    assert warner.seen == 1002
