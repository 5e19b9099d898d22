"""Reading what the machine sends: replies and published samples as their wire models, the
usual msgpack payload in one unpack and one validation, anything else through the codec (which
says why it is not the model); an error reply is `CommandRefused`, anything broken `BadReply`."""

from __future__ import annotations

from typing import TypeVar

import msgpack
import zenoh
from pydantic import BaseModel, ValidationError

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import CalibrationRecord
from ride_machine.schema.codec import (
    MAX_PAYLOAD_BYTES,
    MAX_REPLY_BYTES,
    DecodeError,
    Format,
    decode,
)
from ride_machine.schema.commands import CheckResult, Reply
from ride_machine.schema.completion import Completion
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import Status

from .errors import BadReply, CommandRefused

M = TypeVar("M", bound=BaseModel)

Update = Status | IoValue | AxisRecord | CycleDiag | Completion | CalibrationRecord
"""What a machine publishes that a Rider follows (`watch`, `subscribe`)."""

MSGPACK = zenoh.Encoding(Format.MSGPACK.value)
"""Prebuilt: a request does not parse its encoding string."""


def decode_reply(reply: zenoh.Reply, model: type[M]) -> M:
    """A query's reply as `model`; an error reply is `CommandRefused` (`BadReply` if it is not
    even a `Reply`)."""
    sample = reply.ok
    if sample is None:
        err = reply.err
        data = err.payload.to_bytes() if err is not None else b""
        fmt = format_of(err.encoding if err is not None else None)
        try:
            refused = decode(Reply, data, fmt)
        except DecodeError as exc:
            raise BadReply(f"error reply: {data[:200]!r}") from exc
        raise CommandRefused(refused)
    return decode_ok(sample, model)


def decode_ok(sample: zenoh.Sample, model: type[M]) -> M:
    """A reply's sample as `model`; `BadReply` (or `CommandRefused` for an error `Reply`)
    when it is none (`read`, else the long way, which says why)."""
    data = sample.payload.to_bytes()
    encoding = sample.encoding
    result = read(data, encoding, model, MAX_REPLY_BYTES)
    if result is not None:
        return result
    fmt = format_of(encoding)
    try:
        return decode(model, data, fmt, MAX_REPLY_BYTES)
    except DecodeError as exc:
        # An error reply on a key that normally carries `model` (e.g. unknown parameter).
        try:
            refused = decode(Reply, data, fmt)
        except DecodeError:
            raise BadReply(f"{sample.key_expr}: {exc.error.message}") from exc
        if refused.success:
            raise BadReply(f"{sample.key_expr}: {exc.error.message}") from exc
        raise CommandRefused(refused) from exc
    except ValidationError as exc:  # pragma: no cover - decode wraps these
        raise BadReply(str(exc)) from exc


def read(data: bytes, encoding: zenoh.Encoding, model: type[M], limit: int) -> M | None:
    """`data` as `model` in one unpack and one validation by the model's validator (what
    `model_validate` calls, without its wrapper): the usual msgpack payload, at two thirds of
    `decode`'s cost run hot. None for anything else (another encoding, too large, not a map,
    invalid): the caller decodes that with `decode`, which says why (BENCHMARKS.md, section 9)."""
    if encoding == MSGPACK and len(data) <= limit:
        try:
            raw = msgpack.unpackb(data, raw=False, strict_map_key=True)
            if type(raw) is dict:
                result: M = model.__pydantic_validator__.validate_python(raw)
                return result
        except (ValueError, RecursionError, msgpack.UnpackException, ValidationError):
            pass
    return None


def decode_sample(sample: zenoh.Sample, model: type[M], limit: int) -> M:
    """A published sample as `model` (`read`, else `decode`, which says why); `BadReply`
    naming its key when it is none."""
    data = sample.payload.to_bytes()
    encoding = sample.encoding
    result = read(data, encoding, model, limit)
    if result is not None:
        return result
    try:
        return decode(model, data, format_of(encoding), limit)
    except DecodeError as exc:
        raise BadReply(f"{sample.key_expr}: {exc.error.message}") from exc


def format_of(encoding: zenoh.Encoding | None) -> Format:
    return Format.JSON if str(encoding or "").startswith(Format.JSON) else Format.MSGPACK


def decode_update(sample: zenoh.Sample) -> Update | None:
    """A published sample as its wire model; None for a key that carries none of them.

    Raises `BadReply` for data that does not decode as the key's model."""
    key = str(sample.key_expr)
    model: type[BaseModel]
    if key.endswith("/status"):
        model = Status
    elif "/io/" in key:
        model = IoValue
    elif "/axis/" in key:
        model = AxisRecord
    elif key.endswith("/diag/cycle"):
        model = CycleDiag
    elif "/done/" in key:
        model = Completion
    elif key.endswith("/calibration"):
        model = CalibrationRecord
    else:
        return None
    result = decode_sample(sample, model, MAX_PAYLOAD_BYTES)
    assert isinstance(
        result, Status | IoValue | AxisRecord | CycleDiag | Completion | CalibrationRecord
    )
    return result


def zenoh_timeout(reply: zenoh.Reply) -> bool:
    """Zenoh's own end of a query nobody answered in time (not a reply from a machine)."""
    return reply.ok is None and reply.err is not None and reply.err.payload.to_bytes() == b"Timeout"


def check_result(reply: Reply) -> CheckResult:
    """The result a check command's reply carries (`BadReply` when it carries none)."""
    if reply.result is None:
        raise BadReply(f"{reply.command} reply carries no result")
    return reply.result
