"""Every numeric field of every request is checked at the edge (issue 58, point 1: a NaN
`timecode` passed both of the machine's age checks and a ride ran): NaN and ±Infinity are
refused at their own path, in JSON and in msgpack alike, and huge or negative values are either
refused or taken as finite numbers, never an exception past the codec."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import msgpack
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import BaseModel

from ride_machine.schema.calibration import CalibrationSet
from ride_machine.schema.codec import DecodeError, Format, decode
from ride_machine.schema.commands import CommandRequest, StartRequest
from ride_machine.schema.params import ParamSet
from ride_machine.schema.sim import SIM_REQUESTS

TID = "t-1"
BASES: list[tuple[type[BaseModel], dict[str, Any]]] = [
    (CommandRequest, {"transaction_id": TID, "timecode": 1.0, "valid_for": 5.0}),
    (
        StartRequest,
        {
            "transaction_id": TID,
            "timecode": 1.0,
            "valid_for": 5.0,
            "session": {"name": "s", "steps": [{"kind": "tilt", "degrees": 10.0}]},
        },
    ),
    (
        CalibrationSet,
        {
            "transaction_id": TID,
            "timecode": 1.0,
            "tilt": {"offset_counts": 1200.0, "gain_counts_per_deg": 40.0},
            "rotate": {"revolution_s": 4.0, "home_arc_deg": 10.0},
        },
    ),
    (ParamSet, {"transaction_id": TID, "value": 1.5}),
    (SIM_REQUESTS["tilt_ai"], {"noise_counts": 1.0}),
    (SIM_REQUESTS["stalls"], {"probability": 0.5, "max_s": 0.1}),
    (SIM_REQUESTS["place"], {"tilt_deg": 10.0, "rotate_deg": 20.0}),
]
"""A valid request of every model that carries a number (floats written as floats: they are
the fields under test)."""


def numeric_paths(node: Any, path: tuple[str | int, ...] = ()) -> Iterator[tuple[str | int, ...]]:
    if isinstance(node, float):
        yield path
    elif isinstance(node, dict):
        for key, value in node.items():
            yield from numeric_paths(value, (*path, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from numeric_paths(value, (*path, i))


def replaced(node: Any, path: tuple[str | int, ...], value: object) -> Any:
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(node, dict):
        return {**node, head: replaced(node[head], rest, value)}
    return [replaced(v, rest, value) if i == head else v for i, v in enumerate(node)]


def pointer(path: tuple[str | int, ...]) -> str:
    return "".join(f"/{p}" for p in path)


CASES = [(model, base, path) for model, base in BASES for path in numeric_paths(base)]


def test_every_base_request_is_valid_and_every_model_with_a_number_is_here() -> None:
    for model, base in BASES:
        decode(model, msgpack.packb(base), Format.MSGPACK)
    assert len(CASES) >= 14


def as_wire(data: Any, fmt: Format) -> bytes:
    if fmt is Format.JSON:
        import json

        return json.dumps(data).encode()  # NaN and Infinity as JSON's extension tokens
    return bytes(msgpack.packb(data))


@pytest.mark.parametrize("fmt", [Format.JSON, Format.MSGPACK])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize(
    ("model", "base", "path"), CASES, ids=[f"{m.__name__}{pointer(p)}" for m, _, p in CASES]
)
def test_no_number_is_refused_at_its_own_path(
    model: type[BaseModel],
    base: dict[str, Any],
    path: tuple[str | int, ...],
    bad: float,
    fmt: Format,
) -> None:
    with pytest.raises(DecodeError) as refused:
        decode(model, as_wire(replaced(base, path, bad), fmt), fmt)
    assert refused.value.error.path.startswith(pointer(path)), refused.value.error


@given(st.sampled_from(CASES), st.sampled_from([1e300, -1e300, -1.0, 0.0, 1e18, -1e-300]))
def test_huge_and_negative_numbers_are_refused_or_taken_as_finite(
    case: tuple[type[BaseModel], dict[str, Any], tuple[str | int, ...]], value: float
) -> None:
    model, base, path = case
    try:
        taken = decode(model, as_wire(replaced(base, path, value), Format.MSGPACK), Format.MSGPACK)
    except DecodeError:
        return
    number: Any = taken.model_dump()
    for part in path:
        number = number[part]
    assert isinstance(number, int | float) and math.isfinite(number), (path, number)
