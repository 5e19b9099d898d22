"""Decoding what arrives: format sniffing, size limits, and every decode error with its JSON
pointer (moved from test_codec.py)."""

from __future__ import annotations

import json

import msgpack
import pytest
from pydantic import BaseModel

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.codec import (
    MAX_PAYLOAD_BYTES,
    MAX_REPLY_BYTES,
    DecodeError,
    Format,
    decode,
    decode_raw,
    encode,
    json_pointer,
    pack,
    sniff_format,
    validate,
)
from ride_machine.schema.commands import (
    CommandRequest,
    Session,
    StartRequest,
    TiltStep,
    transaction_id_of,
)
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.schema.events import EventPage
from ride_machine.schema.status import (
    MachineState,
    Status,
)
from tests.schema.test_codec import SAMPLES


# ----------------------------------------------------------------------------------- sniff
@pytest.mark.parametrize(
    ("encoding", "data", "expected"),
    [
        ("application/json", b'{"a": 1}', Format.JSON),
        ("application/json;charset=utf-8", b'{"a": 1}', Format.JSON),
        ("text/json", b'{"a": 1}', Format.JSON),
        ("text/plain", b'{"a": 1}', Format.JSON),
        ("application/msgpack", pack({"a": 1}), Format.MSGPACK),
        ("application/x-msgpack", pack({"a": 1}), Format.MSGPACK),
        # What the zenoh CLI and z_get send: JSON text with the default encoding.
        ("zenoh/bytes", b'{"transaction_id": "t1"}', Format.JSON),
        ("zenoh/bytes", b'  \n {"transaction_id": "t1"}', Format.JSON),
        ("zenoh/bytes", b"[1, 2]", Format.JSON),
        ("zenoh/bytes", pack({"transaction_id": "t1"}), Format.MSGPACK),
        (None, b'{"transaction_id": "t1"}', Format.JSON),
        (None, pack({"transaction_id": "t1"}), Format.MSGPACK),
        ("", pack({}), Format.MSGPACK),
        (None, b"", Format.MSGPACK),
    ],
)
def test_sniff_format(encoding: str | None, data: bytes, expected: Format) -> None:
    assert sniff_format(data, encoding) is expected


def test_json_text_with_default_encoding_decodes_to_a_request() -> None:
    data = b'{"transaction_id": "cli-1", "session": {"steps": [{"kind": "tilt", "degrees": 30}]}}'
    request = decode(StartRequest, data, sniff_format(data, "zenoh/bytes"))
    assert request.transaction_id == "cli-1"
    assert request.session is not None
    assert request.session.steps == [TiltStep(degrees=30.0)]
    assert request.session.name == "default"


def test_a_msgpack_map_never_sniffs_as_json() -> None:
    for size in (0, 1, 15, 16, 70000):
        data = pack({f"k{i}": i for i in range(size)})
        assert sniff_format(data, None) is Format.MSGPACK


# --------------------------------------------------------------------------------- errors
def decode_error(model: type[BaseModel], data: bytes, fmt: Format) -> Error:
    with pytest.raises(DecodeError) as info:
        decode(model, data, fmt)
    assert str(info.value) == info.value.error.message
    return info.value.error


@pytest.mark.parametrize("fmt", list(Format))
def test_oversize_payload_is_refused_before_parsing(fmt: Format) -> None:
    big = StartRequest(transaction_id="big", session=Session(steps=[TiltStep(degrees=1.0)] * 100))
    padding = b" " * MAX_PAYLOAD_BYTES if fmt is Format.JSON else b""
    data = encode(big, fmt) + padding + (b"" if padding else b"\x00" * MAX_PAYLOAD_BYTES)
    error = decode_error(StartRequest, data, fmt)
    assert error.code is ErrorCode.PAYLOAD_TOO_LARGE
    assert str(MAX_PAYLOAD_BYTES) in error.message
    assert str(len(data)) in error.message


def test_payload_at_the_limit_is_accepted() -> None:
    head = b'{"transaction_id": "edge"}'
    data = head + b" " * (MAX_PAYLOAD_BYTES - len(head))
    assert len(data) == MAX_PAYLOAD_BYTES
    assert decode(CommandRequest, data, Format.JSON).transaction_id == "edge"


@pytest.mark.parametrize(
    ("data", "fmt"),
    [
        (b"\xc1", Format.MSGPACK),  # a byte msgpack never uses
        (pack({"transaction_id": "t1"})[:-2], Format.MSGPACK),  # truncated
        (pack({"transaction_id": "t1"}) + b"\x01", Format.MSGPACK),  # trailing bytes
        (b"", Format.MSGPACK),
        (b'{"transaction_id": ', Format.JSON),
        (b'{"transaction_id": "t1"} x', Format.JSON),
        (b"\xff\xfe{}", Format.JSON),  # not UTF-8
        (b"", Format.JSON),
        (b"[" * 100_000 + b"]" * 100_000, Format.JSON),  # nesting bomb (over the size limit)
        (b"[" * 30_000 + b"]" * 30_000, Format.JSON),  # nesting bomb (under it)
    ],
    ids=[
        "msgpack-reserved-byte",
        "msgpack-truncated",
        "msgpack-trailing",
        "msgpack-empty",
        "json-truncated",
        "json-trailing",
        "json-not-utf8",
        "json-empty",
        "json-deep-large",
        "json-deep",
    ],
)
def test_invalid_bytes_give_a_clear_error(data: bytes, fmt: Format) -> None:
    error = decode_error(CommandRequest, data, fmt)
    assert error.code in (ErrorCode.BAD_PAYLOAD, ErrorCode.PAYLOAD_TOO_LARGE)
    if len(data) <= MAX_PAYLOAD_BYTES:
        assert error.code is ErrorCode.BAD_PAYLOAD
        assert fmt.name.lower() in error.message


def test_msgpack_map_with_non_string_keys_is_refused() -> None:
    data = msgpack.packb({1: "x"})
    error = decode_error(CommandRequest, data, Format.MSGPACK)
    assert error.code is ErrorCode.BAD_PAYLOAD


@pytest.mark.parametrize("raw", [[1, 2], "text", 42, None, True])
def test_a_request_must_be_a_map(raw: object) -> None:
    for fmt in Format:
        data = json.dumps(raw).encode() if fmt is Format.JSON else pack(raw)
        error = decode_error(CommandRequest, data, fmt)
        assert error.code is ErrorCode.BAD_PAYLOAD
        assert error.message.startswith("expected a JSON object (or a msgpack map)")
        assert error.path == ""


def start(session: object, **extra: object) -> dict[str, object]:
    return {"transaction_id": "t1", "session": session, **extra}


def steps(*items: object) -> dict[str, object]:
    return {"steps": list(items)}


TILT = {"kind": "tilt", "degrees": 45.0}
BAD_FIELDS = [
    ("tid-type", {"transaction_id": 123}, "/transaction_id"),
    ("tid-missing", {}, "/transaction_id"),
    ("tid-empty", {"transaction_id": ""}, "/transaction_id"),
    ("tid-too-long", {"transaction_id": "x" * 65}, "/transaction_id"),
    ("tid-bad-chars", {"transaction_id": "has space"}, "/transaction_id"),
    ("timecode-type", {"transaction_id": "t", "timecode": "now"}, "/timecode"),
    ("unknown-top", {"transaction_id": "t", "speed": 3}, "/speed"),
    ("degrees-string", start(steps({"kind": "tilt", "degrees": "45"})),
     "/session/steps/0/degrees"),
    ("degrees-missing", start(steps({"kind": "tilt"})), "/session/steps/0/degrees"),
    ("degrees-second-step", start(steps(TILT, {"kind": "tilt", "degrees": [1]})),
     "/session/steps/1/degrees"),
    ("revolutions-zero", start(steps(TILT, {"kind": "rotate", "revolutions": 0})),
     "/session/steps/1/revolutions"),
    ("revolutions-float", start(steps({"kind": "rotate", "revolutions": 2.5})),
     "/session/steps/0/revolutions"),
    ("revolutions-bool", start(steps({"kind": "rotate", "revolutions": True})),
     "/session/steps/0/revolutions"),
    ("revolutions-huge", start(steps({"kind": "rotate", "revolutions": 10**6})),
     "/session/steps/0/revolutions"),
    ("direction-unknown", start(steps({"kind": "rotate", "direction": "up"})),
     "/session/steps/0/direction"),
    ("step-unknown-field", start(steps({"kind": "tilt", "degrees": 1, "speed": 2})),
     "/session/steps/0/speed"),
    ("step-kind-unknown", start(steps({"kind": "jump"})), "/session/steps/0"),
    ("step-kind-missing", start(steps({"degrees": 1})), "/session/steps/0"),
    ("steps-empty", start(steps()), "/session/steps"),
    ("steps-too-many", start(steps(*[TILT] * 101)), "/session/steps"),
    ("steps-not-list", start({"steps": TILT}), "/session/steps"),
    ("session-name-empty", start({"name": "", "steps": [TILT]}), "/session/name"),
    ("session-unknown-field", start({"steps": [TILT], "loop": True}), "/session/loop"),
    ("session-not-map", start("default"), "/session"),
]  # fmt: skip


@pytest.mark.parametrize("fmt", list(Format))
@pytest.mark.parametrize(("raw", "path"), [(r, p) for _, r, p in BAD_FIELDS],
                         ids=[i for i, _, _ in BAD_FIELDS])  # fmt: skip
def test_bad_field_names_its_json_pointer(raw: dict[str, object], path: str, fmt: Format) -> None:
    data = json.dumps(raw).encode() if fmt is Format.JSON else pack(raw)
    error = decode_error(StartRequest, data, fmt)
    assert error.code is ErrorCode.BAD_PAYLOAD
    assert error.path == path
    assert error.message.startswith(f"{path}: ")


@pytest.mark.parametrize("text", [b"NaN", b"Infinity", b"-Infinity"])
def test_non_finite_degrees_are_refused(text: bytes) -> None:
    data = (
        b'{"transaction_id": "t", "session": {"steps": [{"kind": "tilt", "degrees": %s}]}}' % text
    )
    error = decode_error(StartRequest, data, Format.JSON)
    assert error.path == "/session/steps/0/degrees"
    assert "finite" in error.message
    packed = pack(start(steps({"kind": "tilt", "degrees": float(text)})))
    assert decode_error(StartRequest, packed, Format.MSGPACK).path == "/session/steps/0/degrees"


def test_several_bad_fields_report_the_first_and_a_count() -> None:
    raw = {"transaction_id": 1, "timecode": "x", "extra": 0}
    error = decode_error(StartRequest, pack(raw), Format.MSGPACK)
    assert error.path == "/transaction_id"
    assert "(and 2 more)" in error.message


def test_decode_error_keeps_the_raw_data_for_the_reply() -> None:
    raw = {"transaction_id": "keep-me", "session": 5}
    with pytest.raises(DecodeError) as info:
        validate(StartRequest, raw)
    assert info.value.raw == raw
    assert transaction_id_of(info.value.raw) == "keep-me"


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        ({"transaction_id": "t9"}, "t9"),
        ({"transaction_id": ""}, None),
        ({"transaction_id": "x" * 65}, None),
        ({"transaction_id": 5}, None),
        ({}, None),
        (["transaction_id"], None),
        (None, None),
    ],
)
def test_transaction_id_of_undecodable_requests(raw: object, expected: str | None) -> None:
    assert transaction_id_of(raw) == expected


def test_readers_ignore_fields_from_newer_senders() -> None:
    status = Status(machine_id="m1", state=MachineState.DONE, seq=3, cycle=3, time=3.0)
    plain = {**status.model_dump(mode="json"), "from_the_future": {"x": 1}}
    assert decode(Status, pack(plain), Format.MSGPACK) == status
    axis = next(s for s in SAMPLES if isinstance(s, AxisRecord))
    record = {**axis.model_dump(mode="json"), "acceleration_fb": 1.0, "version": 2}
    assert decode(AxisRecord, json.dumps(record).encode(), Format.JSON).version == 2


def test_requests_refuse_coercion_that_readers_allow() -> None:
    # Requests are strict: "1" is not a number...
    with pytest.raises(DecodeError):
        decode_raw_validate(CommandRequest, {"transaction_id": "t", "timecode": "1"})
    # ...but an integer is a fine float.
    assert decode_raw_validate(CommandRequest, {"transaction_id": "t", "timecode": 1}).timecode == 1


def decode_raw_validate(model: type[CommandRequest], raw: dict[str, object]) -> CommandRequest:
    return validate(model, decode_raw(pack(raw), Format.MSGPACK))


@pytest.mark.parametrize(
    ("loc", "pointer"),
    [
        ((), ""),
        (("session", "steps", 0, "tilt", "degrees"), "/session/steps/0/degrees"),
        (("session", "steps", 2, "rotate", "revolutions"), "/session/steps/2/revolutions"),
        (("a/b", "c~d"), "/a~1b/c~0d"),
        (["tilt", "x"], "/tilt/x"),  # a real field called "tilt" is kept
    ],
)
def test_json_pointer(loc: tuple[int | str, ...], pointer: str) -> None:
    assert json_pointer(loc) == pointer


@pytest.mark.parametrize("fmt", list(Format))
def test_a_reply_larger_than_a_request_reads_within_the_reply_limit(fmt: Format) -> None:
    """A page of history may be up to 256 KiB: the Rider reads replies with MAX_REPLY_BYTES,
    while requests keep the 64 KiB bound."""
    page = {"machine_id": "m1", "events": [], "more": False, "pad": "x" * (200 * 1024)}
    data = json.dumps(page).encode() if fmt is Format.JSON else msgpack.packb(page)
    assert MAX_PAYLOAD_BYTES < len(data) < MAX_REPLY_BYTES
    assert decode_error(EventPage, data, fmt).code is ErrorCode.PAYLOAD_TOO_LARGE
    assert decode(EventPage, data, fmt, MAX_REPLY_BYTES).machine_id == "m1"
    with pytest.raises(DecodeError, match=f"the limit is {MAX_REPLY_BYTES}"):
        decode(EventPage, data + b" " * MAX_REPLY_BYTES, fmt, MAX_REPLY_BYTES)
