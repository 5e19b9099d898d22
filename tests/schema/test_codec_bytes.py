"""`encode` writes the very bytes pydantic's `model_dump` / `model_dump_json` would.

`encode` takes the serializer directly and packs with a packer kept per thread (less time per
command reply); the bytes on the wire must not change by a single one, for every reply shape
and every wire model.
"""

from __future__ import annotations

import math
import threading

import msgpack
import pytest
from pydantic import BaseModel

from ride_machine.schema.codec import Format, dump_json, encode, pack
from ride_machine.schema.commands import CheckResult, Command, Reply, ReplyCode
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.schema.status import MachineState
from tests.schema.test_codec import IDS, SAMPLES


def reference(model: BaseModel, fmt: Format) -> bytes:
    """What `encode` wrote before: pydantic's dump, then `msgpack.packb`."""
    if fmt is Format.JSON:
        return model.model_dump_json().encode()
    data: bytes = msgpack.packb(model.model_dump(mode="json"), use_bin_type=True)
    return data


def replies() -> list[Reply]:
    """Every shape a command reply takes: each success code, each check result, each error
    code (with and without a path), no state, no ids, echoed and non-finite timecodes, text
    that JSON and msgpack escape differently."""
    return success_replies() + error_replies() + odd_timecode_replies()


def success_replies() -> list[Reply]:
    """Each success code, then each check result."""
    shapes: list[Reply] = []
    for code in ReplyCode:
        if code is ReplyCode.RESP_ERROR:
            continue
        shapes.append(
            Reply(
                transaction_id="t-1",
                command=Command.HOME.value,
                timecode=1700000000.123456,
                request_timecode=1699999999.5,
                success=True,
                code=code,
                state=MachineState.HOMING,
            )
        )
    for ok, tilt, rotate in [(True, True, True), (False, True, False), (False, False, False)]:
        shapes.append(
            Reply(
                transaction_id="c/1",
                command=Command.CHECK_HOME.value,
                timecode=2.0,
                success=True,
                code=ReplyCode.RESP_CHECK,
                state=MachineState.IDLE,
                result=CheckResult(ok=ok, tilt=tilt, rotate=rotate),
            )
        )
    return shapes


def error_replies() -> list[Reply]:
    """Each error code with and without a path, no state, no ids, escaped text."""
    shapes: list[Reply] = []
    for i, code in enumerate(ErrorCode):
        shapes.append(
            Reply.failure(
                Error(code=code, message=f'{code.value}: «ünïcode» "quoted"\n\t\x00 {i}'),
                transaction_id=None if i % 3 == 0 else f"tx{i}",
                command=None if i % 4 == 0 else Command.START.value,
                timecode=1234.5 + i,
                state=None if i % 2 else MachineState.FAULT_ESTOP,
                request_timecode=None if i % 5 else float(i),
            )
        )
        shapes.append(
            Reply.failure(
                Error(code=code, message="bad field", path="/session/steps/0/degrees"),
                transaction_id="t",
                command=Command.START.value,
                timecode=0.0,
            )
        )
    return shapes


def odd_timecode_replies() -> list[Reply]:
    """Non-finite, negative-zero and extreme timecodes, echoed."""
    shapes: list[Reply] = []
    for odd in (math.inf, -math.inf, math.nan, -0.0, 1e308, 5e-324):
        shapes.append(
            Reply(
                transaction_id="t",
                command="Stop",
                timecode=odd,
                request_timecode=odd,
                success=True,
                code=ReplyCode.RESP_DONE,
            )
        )
    return shapes


REPLIES = replies()


@pytest.mark.parametrize("fmt", list(Format))
@pytest.mark.parametrize("reply", REPLIES, ids=[f"reply-{i}" for i in range(len(REPLIES))])
def test_every_reply_shape_encodes_to_the_same_bytes_as_pydantic(reply: Reply, fmt: Format) -> None:
    assert encode(reply, fmt) == reference(reply, fmt)


@pytest.mark.parametrize("fmt", list(Format))
@pytest.mark.parametrize("model", SAMPLES, ids=IDS)
def test_every_wire_model_encodes_to_the_same_bytes_as_pydantic(
    model: BaseModel, fmt: Format
) -> None:
    assert encode(model, fmt) == reference(model, fmt)


def test_the_packer_is_clean_after_a_value_it_cannot_pack() -> None:
    with pytest.raises(TypeError):
        pack({"a": object()})
    assert pack({"b": 1}) == msgpack.packb({"b": 1}, use_bin_type=True)


def test_threads_encoding_at_once_each_get_their_own_bytes() -> None:
    """A packer is not thread-safe: each thread has its own, so concurrent replies never mix."""
    expected = [reference(r, Format.MSGPACK) for r in REPLIES]
    wrong: list[int] = []
    start = threading.Barrier(4)

    def work() -> None:
        start.wait()
        for _ in range(50):
            for i, r in enumerate(REPLIES):
                if encode(r) != expected[i]:
                    wrong.append(i)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert not wrong


@pytest.mark.parametrize(
    "model", SAMPLES + REPLIES, ids=IDS + [f"reply-{i}" for i in range(len(REPLIES))]
)
def test_dump_json_is_model_dump_json(model: BaseModel) -> None:
    """The event log stores `dump_json(details)`: the text `model_dump_json` gave."""
    assert dump_json(model) == model.model_dump_json()
