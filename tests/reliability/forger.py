"""A hostile peer for the access-control tests: `python -m tests.reliability.forger …`.

It opens its own Zenoh session with the `RIDER_ZENOH_*` credentials it is given (any identity,
or none), listens on its own endpoint with gossip on (so other peers could be told about it and
dial it), and pretends to be what it is not: it holds liveliness tokens, answers queries with a
fake "accepted" reply, publishes a fake IDLE status and puts Riders' deadman heartbeats. It
prints `ready <zid>` once everything is declared and exits by itself after `--duration` seconds
(or on SIGTERM/SIGKILL).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import zenoh

from ride_machine.common.credentials import RIDER, zenoh_settings
from ride_machine.schema.codec import Format, encode
from ride_machine.schema.commands import Reply, ReplyCode
from ride_machine.schema.status import MachineState, SessionProgress, Status

FAKE_TX = "forged"
FORGED_SEQ = 10**9
"""The sequence number of every forged status (a real one never gets there)."""


def fake_status(machine_id: str, session_name: str | None = None) -> bytes:
    session = None
    if session_name is not None:
        session = SessionProgress(name=session_name, step_index=0, step_count=2)
    status = Status(
        machine_id=machine_id,
        state=MachineState.IDLE,
        session=session,
        warnings=[session_name] if session_name is not None else [],
        seq=FORGED_SEQ,
        cycle=1,
        time=time.time(),
    )
    return encode(status)


def fake_reply() -> bytes:
    return encode(
        Reply(
            transaction_id=FAKE_TX,
            command="start",
            timecode=time.time(),
            success=True,
            code=ReplyCode.RESP_START_ACCEPTED,
        )
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="forger")
    p.add_argument("--connect", action="append", default=[])
    p.add_argument("--listen", default="tcp/127.0.0.1:0")
    p.add_argument("--token", action="append", default=[], help="liveliness token to hold")
    p.add_argument("--queryable", action="append", default=[], help="key to answer")
    p.add_argument("--put", action="append", default=[], help="status key to publish on")
    p.add_argument("--beat", action="append", default=[], help="heartbeat key to put on")
    p.add_argument("--machine-id", default="m1")
    p.add_argument(
        "--session-name",
        type=json.loads,
        help="a session name (and warning) in the forged status, as a JSON string (NUL-safe)",
    )
    p.add_argument("--duration", type=float, default=30.0)
    args = p.parse_args(argv)

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([args.listen]))
    conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "true")
    conf.insert_json5("transport/link/tx/lease", "1000")
    for setting, value in zenoh_settings(RIDER).items():
        conf.insert_json5(setting, value)

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    reply = fake_reply()

    def answer(query: zenoh.Query) -> None:
        # A status query gets the forged status, anything else a forged "accepted".
        is_status = str(query.key_expr).endswith("/status")
        body = fake_status(args.machine_id, args.session_name) if is_status else reply
        query.reply(query.key_expr, body, encoding=Format.MSGPACK.value)

    with zenoh.open(conf) as session:
        held = [session.liveliness().declare_token(k) for k in args.token]
        held += [session.declare_queryable(k, answer) for k in args.queryable]
        pubs = [session.declare_publisher(k) for k in args.put]
        beats = [session.declare_publisher(k) for k in args.beat]
        print(f"ready {session.zid()}", flush=True)
        deadline = time.monotonic() + args.duration
        while not stop.is_set() and time.monotonic() < deadline:
            for pub in pubs:
                pub.put(
                    fake_status(args.machine_id, args.session_name), encoding=Format.MSGPACK.value
                )
            for beat in beats:
                beat.put(b"")  # a deadman heartbeat, as a Rider sends it
            stop.wait(0.05)
        for h in held:
            h.undeclare()
        for pub in pubs + beats:
            pub.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())
