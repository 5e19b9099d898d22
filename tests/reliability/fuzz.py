"""Hypothesis strategies for malformed messages, and what every queryable owes each one.

A payload is drawn once (mostly a valid request broken on purpose: a field dropped, a wrong
type, an out-of-range value, an unknown field, a bad transaction id, nested garbage, or no map
at all; sometimes plain junk or torn bytes, under a right or a lying encoding) and fanned out to
every queryable of the daemon. Each key gets an expected outcome: an `ERROR` (exactly one reply,
an error) or an `ANSWER` (the normal reply of a read-only key). A payload the wire schema would
accept where it acts (a valid command, a valid write of a real parameter, a valid fault) is
left out, decoded here exactly as the daemon decodes it, so nothing in the fuzz run moves.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from enum import Enum
from typing import Any

import msgpack
from hypothesis import strategies as st

from ride_machine.schema.codec import DecodeError, Format, decode_raw, sniff_format, validate
from ride_machine.schema.commands import REQUEST_MODELS, Command
from ride_machine.schema.params import ParamSet
from ride_machine.schema.sim import SIM_REQUESTS
from ride_machine.sim import faults as simfaults


class Expect(Enum):
    ERROR = "error"
    ANSWER = "answer"


@dataclass(frozen=True)
class Case:
    key: str
    payload: bytes
    encoding: str | None
    expect: Expect


VALID: dict[str, dict[str, Any]] = {
    "command": {"transaction_id": "fz-1", "timecode": 1.5, "valid_for": 2.0, "rider": None},
    "start": {
        "transaction_id": "fz-2",
        "session": {
            "name": "fuzz",
            "steps": [
                {"kind": "tilt", "degrees": 10.0},
                {"kind": "rotate", "direction": "cw", "revolutions": 2},
            ],
        },
    },
    "param": {"transaction_id": "fz-3", "value": 1.0, "persist": False, "reset": False},
    "estop": {"pressed": True},
    "home": {"axis": "rotate", "stuck": "open"},
    "tilt_ai": {"frozen": True, "noise_counts": 3.0},
    "stall": {"axis": "tilt", "stalled": True},
    "clear": {"transaction_id": "fz-4"},
}

SCALARS = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
    | st.binary(max_size=8)
)
ANY = st.recursive(
    SCALARS,
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=8,
)
EXTREMES = st.sampled_from(
    [0, -1, 1001, 30001.0, -(2**63), 2**64 - 1, 1e308, -1e308, float("nan"), float("inf")]
)
BAD_IDS = st.sampled_from(["", "x" * 65, "has space", "ünï", "a\nb", "t;drop", "*", "a/**"])


def _deep(depth: int) -> Any:
    value: Any = "bottom"
    for n in range(depth):
        value = [value] if n % 2 else {"k": value}
    return value


NESTED = st.integers(min_value=5, max_value=200).map(_deep)


def _paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _paths(v, (*prefix, i))
    return out


def _parent(root: Any, path: tuple[Any, ...]) -> Any:
    for part in path[:-1]:
        root = root[part]
    return root


@st.composite
def broken(draw: st.DrawFn, valid: dict[str, Any]) -> Any:
    """`valid` with one to three things wrong with it."""
    data: Any = copy.deepcopy(valid)
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(
            st.sampled_from(["drop", "retype", "range", "unknown", "id", "nested", "not-a-map"])
        )
        paths = _paths(data)
        if kind == "not-a-map" or not isinstance(data, dict):
            data = draw(ANY.filter(lambda v: not isinstance(v, dict)))
            continue
        if kind == "unknown":
            name = draw(st.text(min_size=1, max_size=10))
            data[name] = draw(ANY)
        elif kind == "id":
            data["transaction_id"] = draw(BAD_IDS)
        elif paths:
            path = draw(st.sampled_from(paths))
            parent = _parent(data, path)
            if kind == "drop":
                del parent[path[-1]]
            elif kind == "retype":
                parent[path[-1]] = draw(ANY)
            elif kind == "range":
                parent[path[-1]] = draw(EXTREMES)
            else:
                parent[path[-1]] = draw(NESTED)
    return data


RIGHT_ENCODINGS = {
    "msgpack": [None, Format.MSGPACK.value, Format.MSGPACK.value, "zenoh/bytes", Format.JSON.value],
    "json": [None, Format.JSON.value, Format.JSON.value, "text/plain", Format.MSGPACK.value],
}
"""Mostly what a client would declare; now and then the other format's name (a lie)."""


@st.composite
def encoded(draw: st.DrawFn, raw: Any) -> tuple[bytes, str | None]:
    """Plain data as msgpack or JSON bytes (mostly well-formed), or garbage and torn bytes."""
    fmt = draw(st.sampled_from(["msgpack", "msgpack", "json", "json", "garbage", "truncated"]))
    if fmt == "garbage":
        return draw(st.binary(min_size=1, max_size=64)), draw(st.sampled_from(ALL_ENCODINGS))
    try:
        if fmt == "truncated" or draw(st.booleans()):
            data = msgpack.packb(raw, use_bin_type=True)
            kind = "msgpack"
        else:
            data = json.dumps(raw).encode()
            kind = "json"
    except (TypeError, ValueError, OverflowError):  # bytes in JSON, too-big ints
        return draw(st.binary(min_size=1, max_size=64)), None
    if fmt == "truncated" and len(data) > 1:
        data = data[: draw(st.integers(1, len(data) - 1))]
    return data, draw(st.sampled_from(RIGHT_ENCODINGS[kind]))


ALL_ENCODINGS = [None, Format.MSGPACK.value, Format.JSON.value, "text/plain", "zenoh/bytes"]


def _decodes(model: Any, data: bytes, encoding: str | None) -> bool:
    try:
        validate(model, decode_raw(data, sniff_format(data, encoding)))
    except DecodeError:
        return False
    return True


def _sim_decodes(what: str, data: bytes, encoding: str | None) -> bool:
    try:
        simfaults.decode_request(what, data, encoding)
    except DecodeError:
        return False
    return True


@dataclass(frozen=True)
class Payload:
    data: bytes
    encoding: str | None


@st.composite
def payloads(draw: st.DrawFn) -> Payload:
    """A broken version of some valid request (or plain junk), encoded somehow."""
    broken_request = st.sampled_from(list(VALID.values())).flatmap(broken)
    raw = draw(st.one_of(broken_request, broken_request, broken_request, ANY))
    data, encoding = draw(encoded(raw))
    return Payload(data, encoding)


@dataclass(frozen=True)
class Keys:
    """The daemon's key space below `machine/<id>/`, as the fuzz run found it."""

    params: list[str]
    reads: list[str]
    unknown_commands: tuple[str, ...] = ("calibrate", "home/now", "launch", "cmd")
    unknown_params: tuple[str, ...] = ("nope", "tilt.nope", "rider_loss")
    unknown_sims: tuple[str, ...] = ("meteor", "estop/x")


def fan_out(p: Payload, keys: Keys) -> list[Case]:
    """One payload to every queryable, with the outcome each owes it.

    A request the wire schema accepts is left out where it would act (a valid command, a valid
    write of a real parameter, a valid fault): the fuzz run must not drive the machine.
    """
    data, enc = p.data, p.encoding
    out = [
        Case(f"cmd/{c.key}", data, enc, Expect.ERROR)
        for c in Command
        if not _decodes(REQUEST_MODELS[c], data, enc)
    ]
    out += [Case(f"cmd/{name}", data, enc, Expect.ERROR) for name in keys.unknown_commands]
    if not _decodes(ParamSet, data, enc):
        out += [Case(f"params/{name}", data, enc, Expect.ERROR) for name in keys.params]
    out += [Case(f"params/{name}", data, enc, Expect.ERROR) for name in keys.unknown_params]
    out.append(Case("params/**", data, enc, Expect.ERROR))  # a wildcard write
    out += [
        Case(f"sim/{what}", data, enc, Expect.ERROR)
        for what in [*SIM_REQUESTS, *keys.unknown_sims]
        if not _sim_decodes(what, data, enc)
    ]
    out.append(Case("sim/world", data, enc, Expect.ANSWER))
    out += [Case(key, data, enc, Expect.ANSWER) for key in keys.reads]
    return out


def reads_without_payload(keys: Keys) -> list[Case]:
    """The plain reads: a parameter without payload is a read, as is `params/**`."""
    names = [*keys.params, "**", "*", "rider_loss.$*"]
    out = [Case(f"params/{n}", b"", None, Expect.ANSWER) for n in names]
    out += [Case(f"params/{n}", b"", None, Expect.ERROR) for n in keys.unknown_params]
    out += [Case(f"cmd/{c.key}", b"", None, Expect.ERROR) for c in Command]
    return out
