"""A Rider of schema 1 against this machine (schema 2): refused clearly, never half-watched.

A schema-1 Rider names itself `rider=<zid>` and beats on `rider/<zid>/heartbeat`, which this
machine no longer watches (it watches `rider/<login>/<zid>/…`): a motion it asked to supervise
would pause at once, or (without the heartbeat check) run unwatched. Its motion commands are
refused `BAD_PAYLOAD` at `/rider` with what to do; its reads, checks and Stop work as before.
"""

from __future__ import annotations

import time

import pytest

from ride_machine.schema.codec import Format, decode, encode
from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.errors import ErrorCode
from tests.integration.support import module_machine
from tests.procs import Daemon

pytestmark = pytest.mark.integration

REPLY_TIMEOUT_S = 10.0


machine = module_machine("old-rider")


def ask(daemon: Daemon, command: Command, **fields: object) -> Reply:
    """One command as a schema-1 Rider sends it (its token held on the old key)."""
    with daemon.rider(supervise=False) as r:
        zid = str(r.session.zid())
        token = r.session.liveliness().declare_token(f"rider/{zid}/alive")
        try:
            tid = f"old-{command.key.replace('/', '-')}-{time.monotonic_ns()}"
            body = CommandRequest.model_validate({"transaction_id": tid, "rider": zid, **fields})
            replies = list(
                r.session.get(
                    f"{r.base}/cmd/{command.key}",
                    payload=encode(body),
                    encoding=Format.MSGPACK.value,
                    attachment=f"rider={zid}".encode(),
                    timeout=REPLY_TIMEOUT_S,
                )
            )
        finally:
            token.undeclare()
    assert len(replies) == 1 and replies[0].ok is not None, replies
    return decode(Reply, replies[0].ok.payload.to_bytes(), Format.MSGPACK)


def test_a_motion_command_naming_a_schema_1_rider_is_refused_and_says_what_to_do(
    machine: Daemon,
) -> None:
    reply = ask(machine, Command.HOME, timecode=time.time(), valid_for=5.0)
    assert not reply.success and reply.error is not None
    assert reply.error.code is ErrorCode.BAD_PAYLOAD and reply.error.path == "/rider"
    assert "schema 1" in reply.error.message and "update the Rider" in reply.error.message


def test_its_checks_and_stop_are_answered_as_before(machine: Daemon) -> None:
    assert ask(machine, Command.CHECK_HOME).success
    assert ask(machine, Command.STOP).success
