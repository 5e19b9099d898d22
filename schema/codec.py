"""Encode and decode wire models: msgpack by default, JSON for the zenoh CLI and for humans."""

from __future__ import annotations

import json
import threading
from enum import StrEnum
from typing import Any, TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

from .errors import Error, ErrorCode

MAX_PAYLOAD_BYTES = 64 * 1024
"""Larger requests are refused before any parsing."""

MAX_REPLY_BYTES = 1024 * 1024
"""Larger replies are refused by the Rider: a page of history (up to 256 KiB) must fit."""

M = TypeVar("M", bound=BaseModel)


class Format(StrEnum):
    """A payload format, named by the Zenoh encoding that announces it."""

    MSGPACK = "application/msgpack"
    JSON = "application/json"


class DecodeError(Exception):
    """A payload that cannot become the expected model; carries the wire `Error`."""

    def __init__(self, error: Error, raw: Any = None) -> None:
        super().__init__(error.message)
        self.error = error
        self.raw = raw


def sniff_format(data: bytes, encoding: str | None) -> Format:
    """Pick the format of a request: its declared encoding, else JSON text if it looks like it.

    The zenoh CLI and z_get send JSON with the default `zenoh/bytes` encoding; a msgpack map never
    starts with `{` or whitespace, so sniffing cannot confuse the two.
    """
    if encoding:
        base = encoding.split(";", 1)[0]
        if base in (Format.JSON, "text/json", "text/plain"):
            return Format.JSON
        if base in (Format.MSGPACK, "application/x-msgpack"):
            return Format.MSGPACK
    head = data.lstrip()[:1]
    if head in (b"{", b"["):
        return Format.JSON
    if head and head[0] < 0x80 and len(data) <= MAX_PAYLOAD_BYTES:
        # ASCII first: no msgpack map (0x80 and up) starts so; a JSON scalar (`42`, `"x"`,
        # `true`) is JSON text and its error must say "expected a JSON object".
        try:
            json.loads(data)
        except (ValueError, RecursionError):
            return Format.MSGPACK
        return Format.JSON
    return Format.MSGPACK


def encode(model: BaseModel, fmt: Format = Format.MSGPACK) -> bytes:
    """Serialise a model in the given format.

    The same bytes as `model_dump_json().encode()` and `packb(model_dump(mode="json"))`,
    straight from the model's serializer (no wrapper, no str round trip) and through this
    thread's packer: a third less time per command reply (tests/schema/test_codec_bytes.py)."""
    serializer = model.__pydantic_serializer__
    if fmt is Format.JSON:
        return serializer.to_json(model)
    return pack(serializer.to_python(model, mode="json"))


def dump_json(model: BaseModel) -> str:
    """`model.model_dump_json()`'s text, from the serializer directly (an event per command)."""
    text: str = model.__pydantic_serializer__.to_json(model).decode()
    return text


_local = threading.local()


def pack(obj: Any) -> bytes:
    """msgpack bytes of plain data (`packb`'s, through a packer kept per thread: a packer is
    not thread-safe, and it resets itself after each `pack`, also after an error)."""
    try:
        packer = _local.packer
    except AttributeError:
        packer = _local.packer = msgpack.Packer(use_bin_type=True)
    data: bytes = packer.pack(obj)
    return data


def decode_raw(data: bytes, fmt: Format, limit: int = MAX_PAYLOAD_BYTES) -> Any:
    """Bytes to plain data, or `DecodeError` saying why; `limit` bounds the size read."""
    if len(data) > limit:
        raise DecodeError(too_large(len(data), limit))
    try:
        if fmt is Format.JSON:
            return json.loads(data)
        return msgpack.unpackb(data, raw=False, strict_map_key=True)
    except (ValueError, RecursionError, msgpack.UnpackException) as exc:
        # json.JSONDecodeError, UnicodeDecodeError and msgpack's ExtraData are ValueErrors.
        raise DecodeError(
            Error(
                code=ErrorCode.BAD_PAYLOAD,
                message=f"payload is not valid {fmt.name.lower()}: {_short(exc)}",
            )
        ) from exc


def too_large(size: int, limit: int = MAX_PAYLOAD_BYTES) -> Error:
    """The refusal of a payload of `size` bytes, past `limit` (told from its length alone)."""
    return Error(
        code=ErrorCode.PAYLOAD_TOO_LARGE, message=f"payload is {size} bytes, the limit is {limit}"
    )


def validate(model: type[M], raw: Any) -> M:
    """Plain data to a model, or `DecodeError` naming the first bad field as a JSON pointer."""
    if not isinstance(raw, dict):
        raise DecodeError(
            Error(
                code=ErrorCode.BAD_PAYLOAD,
                message=f"expected a JSON object (or a msgpack map), got {_kind(raw)}",
            ),
            raw,
        )
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        path = json_pointer(first["loc"])
        count = exc.error_count()
        more = f" (and {count - 1} more)" if count > 1 else ""
        raise DecodeError(
            Error(
                code=ErrorCode.BAD_PAYLOAD,
                message=f"{path or '/'}: {first['msg']}{more}",
                path=path,
            ),
            raw,
        ) from exc


def decode(model: type[M], data: bytes, fmt: Format, limit: int = MAX_PAYLOAD_BYTES) -> M:
    """Bytes straight to a model (requests: 64 KiB; the Rider reads replies up to 1 MiB)."""
    return validate(model, decode_raw(data, fmt, limit))


def json_pointer(loc: tuple[int | str, ...] | list[int | str]) -> str:
    """A pydantic error location as an RFC 6901 JSON pointer; union tags are skipped."""
    parts: list[str] = []
    for item in loc:
        text = str(item)
        if text in ("tilt", "rotate") and parts and parts[-1].isdigit():
            continue  # the discriminator tag pydantic inserts for a step, not a real field
        parts.append(text.replace("~", "~0").replace("/", "~1"))
    return "".join("/" + p for p in parts)


def _kind(raw: Any) -> str:
    """A JSON-ish name for what came instead of an object."""
    names = {bool: "a boolean", int: "a number", float: "a number", str: "a string"}
    names.update({list: "an array", type(None): "null", bytes: "bytes"})
    return names.get(type(raw), type(raw).__name__)


def _short(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text[:200]
