"""A msgpack codec for the `zenoh` CLI (the zenoh-cli package), shipped with the project.

zenoh-cli loads codecs from the entry-point groups `zenoh_cli.codecs.decoders` and
`zenoh_cli.codecs.encoders` (pyproject.toml registers these two functions), so with this package
installed `zenoh subscribe -k 'machine/**' --decoder msgpack` prints each live sample as one line
of JSON, and `--encoder msgpack` sends JSON text from the command line as msgpack.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import msgpack


def decode_msgpack(key: str, value: bytes) -> str:
    """msgpack bytes as one line of JSON; a JSON payload (a reply to a JSON request) as is."""
    try:
        data = msgpack.unpackb(value, raw=False, strict_map_key=False)
    except (ValueError, msgpack.UnpackException):
        # The machine answers JSON requests in JSON: show those too instead of failing.
        data = json.loads(value)
    return json.dumps(data, default=_jsonable, ensure_ascii=False)


def encode_msgpack(key: str, value: str) -> bytes:
    """JSON text (as typed after `-v`) as msgpack bytes."""
    packed: bytes = msgpack.packb(json.loads(value), use_bin_type=True)
    return packed


def _jsonable(obj: Any) -> Any:
    """What msgpack has and JSON has not: binary as base64 text, extension types tagged."""
    if isinstance(obj, bytes):
        return base64.b64encode(obj).decode()
    if isinstance(obj, msgpack.ExtType):
        return {"ext": obj.code, "data": base64.b64encode(obj.data).decode()}
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")
