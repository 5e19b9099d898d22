"""The Rider's test fixtures: the scripted machine (tests/rider/scripted.py), one Zenoh session
for a test module, cleared for each test."""

from __future__ import annotations

import json
from collections.abc import Iterator

import msgpack
import pytest
import zenoh

from ride_machine.schema.codec import encode
from tests.procs import free_port
from tests.rider.scripted import MSGPACK, Scripted, good_reply


@pytest.fixture(scope="module")
def machine() -> Iterator[Scripted]:
    scripted = Scripted(f"tcp/127.0.0.1:{free_port()}")
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([scripted.endpoint]))

    def on_query(query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        with scripted.lock:
            scripted.payloads.append(payload)
        answer = scripted.answer or (
            lambda q, p: q.reply(
                q.key_expr,
                encode(good_reply(msgpack.unpackb(p)["transaction_id"])),
                encoding=MSGPACK,
            )
        )
        with query:
            answer(query, payload)

    with zenoh.open(conf) as session:
        scripted.session = session
        queryable = session.declare_queryable("machine/m1/cmd/**", on_query)
        try:
            yield scripted
        finally:
            queryable.undeclare()


@pytest.fixture
def scripted(machine: Scripted) -> Iterator[Scripted]:
    machine.answer = None
    machine.payloads.clear()
    yield machine
    machine.answer = None
