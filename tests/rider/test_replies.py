"""The Rider's command path against a scripted machine (tests/rider/scripted.py): a real Zenoh
session on 127.0.0.1 whose queryable records each request and answers what the test tells it to.

The Rider packs its own requests without a model and reads the usual reply in one unpack and
one validation (rider/commands.py `_own_request`, rider/replies.py `decode_ok`); these pin
that the bytes are the model's, and that every reply is still validated (a broken or hostile
one is `BadReply`, an error `Reply` is `CommandRefused`). Which replier is the machine's:
tests/rider/test_repliers.py.
"""

from __future__ import annotations

import contextlib
import queue
import time
from pathlib import Path

import msgpack
import pytest
import zenoh
from pydantic import ValidationError

from ride_machine.rider.client import BadReply, CommandRefused, Update
from ride_machine.schema.codec import MAX_PAYLOAD_BYTES, MAX_REPLY_BYTES, Format, encode
from ride_machine.schema.commands import (
    VALID_FOR_MAX_S,
    CheckResult,
    Command,
    CommandRequest,
    Reply,
    StartRequest,
)
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.schema.status import MachineState, Status
from tests.rider.scripted import (
    BLOCK,
    DROP,
    JSON,
    MSGPACK,
    Scripted,
    good_fields,
    good_reply,
    rider_for,
)


@pytest.mark.parametrize(
    ("timeout", "retries", "supervise"),
    [(2.0, 1, False), (3, 0, True), (0.25, 2, True), (1800.0, 3, False)],
)
def test_a_commands_request_is_the_models_encoding_byte_for_byte(
    scripted: Scripted, tmp_path: Path, timeout: float, retries: int, supervise: bool
) -> None:
    with rider_for(scripted, tmp_path, timeout=timeout, retries=retries, supervise=supervise) as r:
        for command in Command:
            reply = r.command(command)
            assert reply == good_reply(reply.transaction_id)
        sent = list(scripted.payloads)
        ids = set()
        for payload in sent:
            fields = msgpack.unpackb(payload)
            request = CommandRequest.model_validate(fields)  # a valid request, as it was
            assert encode(request) == payload  # the model's own bytes: order, types, all
            assert list(fields) == ["transaction_id", "timecode", "rider", "valid_for"]
            assert request.transaction_id.startswith(f"{r._commands.tag}-")
            assert request.rider == (r.rider_id if supervise else None)
            assert request.valid_for == min(timeout * (retries + 1), VALID_FOR_MAX_S)
            assert isinstance(fields["valid_for"], float)
            ids.add(request.transaction_id)
        assert len(sent) == len(Command) == len(ids)


def test_requests_the_caller_builds_still_go_through_their_model(
    scripted: Scripted, tmp_path: Path
) -> None:
    with rider_for(scripted, tmp_path, timeout=1.0) as r:
        r.start()
        given = CommandRequest(transaction_id="given-1", timecode=None)
        r.command(Command.HOME, given)
    start, home = (msgpack.unpackb(p) for p in scripted.payloads)
    assert encode(StartRequest.model_validate(start)) == scripted.payloads[0]
    assert "session" in start
    assert home["transaction_id"] == "given-1" and home["valid_for"] == 2.0


def test_a_timeout_of_zero_is_refused_by_the_request_model_and_nothing_is_sent(
    scripted: Scripted, tmp_path: Path
) -> None:
    with rider_for(scripted, tmp_path) as r, pytest.raises(ValidationError, match="valid_for"):
        r.command(Command.HOME, timeout=0)
    assert scripted.payloads == []


def test_the_usual_reply_is_the_model_validated_from_its_bytes(
    scripted: Scripted, tmp_path: Path
) -> None:
    """The fast read gives what the codec's decode gives, for msgpack and JSON replies."""
    with rider_for(scripted, tmp_path) as r:
        for fmt, encoding in ((Format.MSGPACK, MSGPACK), (Format.JSON, JSON)):
            scripted.reply_with(encode(good_reply("t-1"), fmt), encoding)
            result = r.check_home()
            assert result == CheckResult(ok=True, tilt=True, rotate=False)
            assert r.command(Command.HOME) == good_reply("t-1")
        # An older or newer machine's extra field is ignored, as the model says.
        scripted.reply_with(good_fields(new_field=[1]))
        assert r.command(Command.HOME) == good_reply("t")


def refused(tid: str) -> Reply:
    return Reply.failure(
        Error(code=ErrorCode.WRONG_STATE, message="not now"),
        transaction_id=tid,
        command="Home",
        timecode=2.0,
        state=MachineState.RUNNING,
    )


HOSTILE: dict[str, tuple[bytes, zenoh.Encoding]] = {
    "not msgpack": (b"\xc1\xc1", MSGPACK),
    "a msgpack array": (msgpack.packb([1, 2, 3]), MSGPACK),
    "a msgpack string": (msgpack.packb("RESP_CHECK"), MSGPACK),
    "trailing bytes": (encode(good_reply("t")) + b"\x00", MSGPACK),
    "a field missing": (
        good_fields(code=DROP),
        MSGPACK,
    ),
    "an unknown code": (
        good_fields(code="RESP_MAYBE"),
        MSGPACK,
    ),
    "a result of the wrong shape": (
        good_fields(result={"ok": [1]}),
        MSGPACK,
    ),
    "an integer map key": (msgpack.packb({1: 2}), MSGPACK),
    "msgpack labelled as JSON": (encode(good_reply("t")), JSON),
    "JSON labelled as msgpack": (encode(good_reply("t"), Format.JSON), MSGPACK),
    "too large": (
        good_fields(pad="x" * MAX_REPLY_BYTES),
        MSGPACK,
    ),
}


@pytest.mark.hazard("H30")
@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_a_broken_or_hostile_reply_is_a_bad_reply(
    scripted: Scripted, tmp_path: Path, case: str
) -> None:
    data, encoding = HOSTILE[case]
    scripted.reply_with(data, encoding)
    with rider_for(scripted, tmp_path, retries=0) as r, pytest.raises(BadReply, match="cmd/home"):
        r.command(Command.HOME)


def test_a_reply_without_its_result_is_a_bad_reply(scripted: Scripted, tmp_path: Path) -> None:
    scripted.reply_with(encode(good_reply("t").model_copy(update={"result": None})))
    with rider_for(scripted, tmp_path) as r, pytest.raises(BadReply, match="no result"):
        r.check_home()


def test_an_error_reply_is_a_refusal_whether_sent_as_a_reply_or_as_an_error(
    scripted: Scripted, tmp_path: Path
) -> None:
    with rider_for(scripted, tmp_path) as r:
        scripted.reply_with(encode(refused("t-1")))
        with pytest.raises(CommandRefused, match="WRONG_STATE: not now") as first:
            r.home()
        assert first.value.reply == refused("t-1")
        assert r.command(Command.HOME, check=False) == refused("t-1")
        scripted.answer = lambda q, _: q.reply_err(encode(refused("t-2")), encoding=MSGPACK)
        with pytest.raises(CommandRefused, match="WRONG_STATE") as second:
            r.home()
        assert second.value.reply == refused("t-2")
        scripted.answer = lambda q, _: q.reply_err(b"\xc1", encoding=MSGPACK)
        with pytest.raises(BadReply, match="error reply"):
            r.home()


def test_a_broken_or_hostile_publication_is_dropped_and_a_good_one_read(
    scripted: Scripted, tmp_path: Path
) -> None:
    """Publications are read the same way (one unpack, one validation, else the codec's
    `decode`): what does not validate as the key's model never reaches the subscriber, nor a
    status larger than a request may be (64 KiB), while the next good one does."""
    good = Status(machine_id="m1", state=MachineState.IDLE, seq=7, cycle=70, time=1.5)
    other = good.model_copy(update={"seq": 666})  # valid itself: only its wrapping is wrong
    fields = msgpack.unpackb(encode(other))
    hostile: list[tuple[bytes, zenoh.Encoding]] = [
        (b"\xc1\xc1", MSGPACK),
        (msgpack.packb([fields]), MSGPACK),
        (msgpack.packb({**fields, "state": "FLYING"}), MSGPACK),
        (msgpack.packb({k: v for k, v in fields.items() if k != "cycle"}), MSGPACK),
        (msgpack.packb({**fields, "estop": {"active": "maybe"}}), MSGPACK),
        (encode(other), JSON),
        (encode(other, Format.JSON), MSGPACK),
        (msgpack.packb({**fields, "pad": "x" * MAX_PAYLOAD_BYTES}), MSGPACK),
    ]
    updates: queue.Queue[Update] = queue.Queue()
    ready = good.model_copy(update={"seq": 1})

    def put(data: bytes, encoding: zenoh.Encoding) -> None:
        assert scripted.session is not None
        scripted.session.put("machine/m1/status", data, encoding=encoding, congestion_control=BLOCK)

    with rider_for(scripted, tmp_path) as r, r.subscribe(("status",), updates.put):
        # The subscription reaches the publishing session a moment after it is declared.
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            put(encode(ready), MSGPACK)
            with contextlib.suppress(queue.Empty):
                if updates.get(timeout=0.1) == ready:
                    break
        for data, encoding in hostile:
            put(data, encoding)
        put(encode(good), MSGPACK)
        put(encode(good, Format.JSON), JSON)
        after = [updates.get(timeout=5.0) for _ in range(2)]
        while after[0] == ready:  # a late copy of the probe
            after = [*after[1:], updates.get(timeout=5.0)]
        assert after == [good, good]  # the first to arrive after: every hostile one dropped
