"""The msgpack codec the package gives the zenoh CLI (live: tests/integration/test_zenoh_cli.py)."""

from __future__ import annotations

import importlib
import json
import tomllib

import msgpack
import pytest

from ride_machine.rider.zenoh_codec import decode_msgpack, encode_msgpack
from tests.procs import REPO


def test_the_package_registers_the_codec_where_zenoh_cli_looks() -> None:
    """zenoh-cli's entry-point groups (the live CLI run: tests/integration/test_zenoh_cli.py)."""
    eps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["entry-points"]
    for group, func in (("decoders", decode_msgpack), ("encoders", encode_msgpack)):
        target = eps[f"zenoh_cli.codecs.{group}"]["msgpack"]
        module, _, name = target.partition(":")
        assert getattr(importlib.import_module(module), name) is func


def test_msgpack_becomes_one_json_line() -> None:
    raw = msgpack.packb({"state": "IDLE", "n": [1, 2.5, None], "blob": b"\x00\xff"})
    line = decode_msgpack("machine/m1/status", raw)
    assert "\n" not in line
    assert json.loads(line) == {"state": "IDLE", "n": [1, 2.5, None], "blob": "AP8="}


def test_a_json_reply_is_shown_as_is() -> None:
    assert json.loads(decode_msgpack("k", b'{"success": true}')) == {"success": True}


def test_encoder_round_trips_json_text() -> None:
    assert msgpack.unpackb(encode_msgpack("k", '{"transaction_id": "t1"}')) == {
        "transaction_id": "t1"
    }


def test_garbage_is_an_error_the_cli_reports() -> None:
    with pytest.raises(ValueError):
        decode_msgpack("k", b"\xc1")
