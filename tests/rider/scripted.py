"""The scripted machine the Rider's reply tests talk to: a real Zenoh session on 127.0.0.1 whose
queryable records each request and answers what the test tells it to (the fixtures `machine`
and `scripted` are in tests/rider/conftest.py), and the good reply it answers by default."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import zenoh

from ride_machine.rider.client import Rider
from ride_machine.schema.codec import Format, encode
from ride_machine.schema.commands import CheckResult, Reply, ReplyCode
from ride_machine.schema.status import MachineState
from tests.procs import write_zenoh_config

MSGPACK = zenoh.Encoding(Format.MSGPACK.value)
JSON = zenoh.Encoding(Format.JSON.value)
BLOCK = zenoh.CongestionControl.BLOCK
"""For the test's own puts: with the default (drop), a put right behind a large one is lost."""


def good_reply(tid: str | None, command: str | None = "CheckHome") -> Reply:
    return Reply(
        transaction_id=tid,
        command=command,
        timecode=1.5,
        request_timecode=1.25,
        success=True,
        code=ReplyCode.RESP_CHECK,
        state=MachineState.IDLE,
        result=CheckResult(ok=True, tilt=True, rotate=False),
    )


def good_fields(**changes: object) -> bytes:
    """A good reply's msgpack with fields changed, added, or (given as `DROP`) removed."""
    fields = {**msgpack.unpackb(encode(good_reply("t"))), **changes}
    data: bytes = msgpack.packb({k: v for k, v in fields.items() if v is not DROP})
    return data


DROP = object()

Answer = Callable[[zenoh.Query, bytes], None]


@dataclass
class Scripted:
    """The scripted machine: `answer(query, payload)` replies; `payloads` holds every request."""

    endpoint: str
    session: zenoh.Session | None = None
    answer: Answer | None = None
    payloads: list[bytes] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def reply_with(self, data: bytes, encoding: zenoh.Encoding = MSGPACK) -> None:
        self.answer = lambda q, _: q.reply(q.key_expr, data, encoding=encoding)


def rider_for(machine: Scripted, tmp_path: Path, **kwargs: object) -> Rider:
    conf = write_zenoh_config(tmp_path)
    return Rider("m1", connect=[machine.endpoint], zenoh_config_path=conf, **kwargs)  # type: ignore[arg-type]
