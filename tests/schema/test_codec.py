"""The wire codec: round trips of every model, format sniffing, and precise decode errors."""

from __future__ import annotations

import importlib
import inspect
import json
import pkgutil

import msgpack
import pytest
from pydantic import BaseModel

import schema
from schema.axes import AxisRecord, PnStatus
from schema.base import OpenWireModel, WireModel
from schema.calibration import (
    CalibrationRecord,
    CalibrationSet,
    CalibrationSource,
    RotateCalibrationSet,
    RotateCalibrationValues,
    TiltCalibrationSet,
    TiltCalibrationValues,
)
from schema.codec import (
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
from schema.commands import (
    DEFAULT_SESSION,
    CheckResult,
    CommandRequest,
    Direction,
    Reply,
    ReplyCode,
    RotateStep,
    Session,
    StartRequest,
    TiltStep,
    transaction_id_of,
)
from schema.completion import Completion, Outcome
from schema.diag import CycleDiag, TimingStats
from schema.errors import Error, ErrorCode
from schema.events import EventPage
from schema.findings import Finding, Findings, Severity
from schema.io import IoKind, IoValue
from schema.params import ParamSet, ParamValue
from schema.sim import (
    SimAxis,
    SimClear,
    SimEstop,
    SimHomeSwitch,
    SimPlace,
    SimStall,
    SimStalls,
    SimTiltSignal,
    SimWorldState,
    SwitchState,
)
from schema.status import (
    AxesFlags,
    EstopInfo,
    Fault,
    FaultCode,
    MachineState,
    MotionRef,
    SessionProgress,
    Status,
)
from tests.schema.event_samples import EVENT_SAMPLES

MIXED = Session(
    name="mixed",
    steps=[
        TiltStep(degrees=30.5),
        RotateStep(direction=Direction.CCW, revolutions=2),
        TiltStep(degrees=0),
    ],
)
ERROR = Error(code=ErrorCode.WRONG_STATE, message="Start is not accepted in RUNNING", path="")
FAULT = Fault(code=FaultCode.ROTATE_HOME_TIMEOUT, message="not seen within 8 s", axis="rotate")
PROGRESS = SessionProgress(
    name="default",
    step_index=1,
    step_count=2,
    step_kind="rotate",
    revolutions_done=2,
    revolutions_total=3,
    tilt_target_deg=45.0,
)
TIMING = TimingStats(last=1e-4, mean=2e-4, min=5e-5, max=1e-3, p50=1.9e-4, p99=9e-4)
IO = IoValue(name="tiltPosition", kind=IoKind.AI, channel="InputValue_1", value=2994, time=12.5)
PARAM = ParamValue(name="tilt.tolerance_deg", value=1.0, default=1.0, persisted=False, unit="°")

SAMPLES: list[BaseModel] = [
    TiltStep(degrees=45.0),
    RotateStep(direction=Direction.CW, revolutions=3),
    DEFAULT_SESSION,
    MIXED,
    CommandRequest(transaction_id="t-1"),
    CommandRequest(transaction_id="a.b:c@d/e+f-1", timecode=1700000000.25, rider="rider-7"),
    StartRequest(transaction_id="s1"),
    StartRequest(transaction_id="s2", session=MIXED, timecode=3.0),
    CheckResult(ok=False, tilt=True, rotate=False),
    MotionRef(transaction_id="h1", command="Home", started_at=5.0),
    CalibrationRecord(
        machine_id="m1",
        tilt=TiltCalibrationValues(
            offset_counts=1194.0,
            gain_counts_per_deg=40.0,
            source=CalibrationSource.MANUAL,
            at=7.5,
        ),
        rotate=RotateCalibrationValues(revolution_s=4.0, home_arc_deg=9.9, speed_dps=90.0),
        complete=True,
        time=8.0,
    ),
    TiltCalibrationValues(offset_counts=1.0, gain_counts_per_deg=2.0),
    RotateCalibrationValues(revolution_s=4.0, home_arc_deg=9.9, speed_dps=90.0, at=1.0),
    TiltCalibrationSet(offset_counts=-3.5, gain_counts_per_deg=2.0),
    RotateCalibrationSet(revolution_s=4.0, home_arc_deg=9.9),
    CalibrationSet(
        transaction_id="cal-1",
        timecode=3.0,
        tilt=TiltCalibrationSet(offset_counts=1194.0, gain_counts_per_deg=40.0),
        rotate=RotateCalibrationSet(revolution_s=4.0, home_arc_deg=9.9),
    ),
    Completion(
        machine_id="m1",
        transaction_id="a.b/c",
        command="Start",
        outcome=Outcome.REFUSED,
        code="NOT_HOME",
        reason="Start refused: tilt not home",
        state=MachineState.WARNING_NOT_HOME,
        rider="r1",
        started_at=5.0,
        time=5.0,
    ),
    Reply(
        transaction_id="t1",
        command="Start",
        timecode=10.0,
        success=True,
        code=ReplyCode.RESP_START_ACCEPTED,
        state=MachineState.RUNNING,
    ),
    Reply(
        transaction_id="t2",
        command="CheckHome",
        timecode=11.0,
        success=True,
        code=ReplyCode.RESP_CHECK,
        state=MachineState.IDLE,
        result=CheckResult(ok=True, tilt=True, rotate=True),
    ),
    Reply.failure(ERROR, transaction_id=None, command=None, timecode=0.0),
    ERROR,
    Error(code=ErrorCode.BAD_PAYLOAD, message="bad", path="/session/steps/0/degrees"),
    FAULT,
    PROGRESS,
    AxesFlags(tilt=True, rotate=False),
    EstopInfo(active=False, latched=True),
    Status(machine_id="m1", state=MachineState.IDLE, seq=1, cycle=1, time=0.0),
    Status(
        machine_id="m1",
        state=MachineState.FAULT_HW,
        previous_state=MachineState.RUNNING,
        session=PROGRESS,
        warnings=["calibration.json: corrupt"],
        fault=FAULT,
        estop=EstopInfo(active=True, latched=True),
        calibrated=AxesFlags(tilt=True, rotate=True),
        homed=AxesFlags(tilt=False, rotate=False),
        tilt_deg=44.6,
        rotate_deg=120.5,
        rider_connected=True,
        seq=99,
        cycle=12345,
        time=1700000000.5,
        uptime_s=123.45,
    ),
    AxisRecord(
        axis="rotate",
        axis_number=0,
        pn_status=int(PnStatus.MOVING | PnStatus.DRIVE_ENABLED),
        cycle=7,
        position_cmd=10.0,
        position_fb=9.5,
        velocity_cmd=90.0,
        velocity_fb=89.9,
        time=1.0,
    ),
    IO,
    IoValue(name="estop", kind=IoKind.DI, channel="I_3", value=True, time=1.0),
    TIMING,
    CycleDiag(
        period_s=0.01,
        cycles=100,
        execution=TIMING,
        jitter=TIMING,
        overruns=2,
        missed_cycles=3,
        commands=4,
        window=100,
        since=0.0,
        time=1.0,
    ),
    PARAM,
    ParamValue(name="machine.mode", value="fast", default="slow", persisted=True, changed_at=5.0),
    ParamSet(transaction_id="p1", value=2.5, persist=True),
    ParamSet(transaction_id="p2", reset=True),
    Finding(category="unknown_key", severity=Severity.ERROR, path="/loop/x", message="no"),
    Findings(
        ok=False,
        findings=[Finding(category="c", severity=Severity.WARNING, path="", message="m")],
    ),
    SimEstop(pressed=True),
    SimHomeSwitch(transaction_id="h", axis=SimAxis.TILT, stuck=SwitchState.CLOSED),
    SimHomeSwitch(axis=SimAxis.ROTATE),
    SimTiltSignal(frozen=True, noise_counts=12.5),
    SimStall(axis=SimAxis.ROTATE, stalled=False),
    SimStalls(probability=0.05, max_s=0.05),
    SimPlace(tilt_deg=-5.0),
    SimClear(),
    SimWorldState(
        time=1.0,
        tilt_deg=2.0,
        rotate_deg=3.0,
        revolutions=0.5,
        estop_pressed=False,
        relays={"O_1": True},
        faults={"tilt_ai_frozen": False},
    ),
    *EVENT_SAMPLES,
]
IDS = [f"{type(m).__name__}-{i}" for i, m in enumerate(SAMPLES)]


def wire_models() -> set[type[BaseModel]]:
    """Every pydantic model defined in the `schema` package."""
    found: set[type[BaseModel]] = set()
    for info in pkgutil.iter_modules(schema.__path__):
        module = importlib.import_module(f"schema.{info.name}")
        for _, obj in inspect.getmembers(module, inspect.isclass):
            if (
                issubclass(obj, BaseModel)
                and obj.__module__ == module.__name__
                and obj not in (WireModel, OpenWireModel)
            ):
                found.add(obj)
    return found


def test_every_wire_model_has_a_round_trip_sample() -> None:
    missing = {m.__name__ for m in wire_models()} - {type(s).__name__ for s in SAMPLES}
    assert not missing, f"add samples for {sorted(missing)}"


@pytest.mark.parametrize("fmt", list(Format))
@pytest.mark.parametrize("model", SAMPLES, ids=IDS)
def test_round_trip(model: BaseModel, fmt: Format) -> None:
    data = encode(model, fmt)
    assert isinstance(data, bytes)
    back = decode(type(model), data, fmt)
    assert back == model
    assert encode(back, fmt) == data
    # The bytes are what they claim to be, and sniffing without an encoding finds the format.
    if fmt is Format.JSON:
        assert isinstance(json.loads(data), dict)
    else:
        assert isinstance(msgpack.unpackb(data), dict)
    assert sniff_format(data, None) is fmt


def test_enums_travel_as_their_string_values() -> None:
    status = Status(machine_id="m1", state=MachineState.RUNNING, seq=1, cycle=1, time=0.0)
    plain = msgpack.unpackb(encode(status))
    assert plain["state"] == "RUNNING"
    assert json.loads(encode(status, Format.JSON))["state"] == "RUNNING"
    reply = Reply.failure(ERROR, transaction_id="x", command="Start", timecode=1.0)
    assert msgpack.unpackb(encode(reply))["error"]["code"] == "WRONG_STATE"


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
