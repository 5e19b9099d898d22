"""A second machine that appears and disappears at random moments, for the default-pick trials.

    python -m tests.site.appearer --id b --peer-config zenoh.json5 --client-config c.json5 \
        --listen tcp/127.0.0.1:PORT --connect tcp/127.0.0.1:A --router tcp/127.0.0.1:R --for 60

Each appearance is what a starting daemon does on the network: a *new* Zenoh session (new
links, gossip, a new zid) with the daemon's own config (alternately a peer that listens and
links to machine `a` and the router, like `fb` in issue 22, and a client of the router), its
`<prefix>/<id>/status` queryable, then its liveliness token `<prefix>/<id>/alive`. A departure
undeclares the token and closes the session. No scan loop runs: presence is all it models.
Prints one JSON line per change, `{"up": <time.time() once declared>}` and
`{"down": <time.time() before undeclaring>}`, and stops after `--for` seconds or on SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

import zenoh


def session_config(path: Path, mode: str, listen: list[str], connect: list[str]) -> zenoh.Config:
    conf = zenoh.Config.from_file(str(path))
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    return conf


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="appearer", description=__doc__)
    p.add_argument("--id", default="b")
    p.add_argument("--prefix", default="machine")
    p.add_argument("--peer-config", type=Path, required=True)
    p.add_argument("--client-config", type=Path, required=True)
    p.add_argument("--listen", required=True, help="where the peer appearance listens")
    p.add_argument("--connect", required=True, help="machine a's endpoint")
    p.add_argument("--router", required=True)
    p.add_argument("--for", dest="duration", type=float, required=True)
    p.add_argument("--up", type=float, nargs=2, default=(0.05, 0.8), metavar=("MIN", "MAX"))
    p.add_argument("--down", type=float, nargs=2, default=(0.05, 0.8), metavar=("MIN", "MAX"))
    p.add_argument("--seed", type=int, default=None)
    args = p.parse_args(argv)
    rng = random.Random(args.seed)
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    configs = [
        session_config(args.peer_config, "peer", [args.listen], [args.connect, args.router]),
        session_config(args.client_config, "client", [], [args.router]),
    ]
    end = time.monotonic() + args.duration
    key = f"{args.prefix}/{args.id}"
    n = 0
    while not stop.is_set() and time.monotonic() < end:
        try:
            session = zenoh.open(configs[n % len(configs)])
        except zenoh.ZError as exc:  # e.g. the router busy past connect.timeout_ms: no appearance
            print(json.dumps({"failed": str(exc)[:200]}), flush=True)
            n += 1
            stop.wait(rng.uniform(*args.down))
            continue
        with session:
            status = session.declare_queryable(f"{key}/status", lambda q: q.drop())
            token = session.liveliness().declare_token(f"{key}/alive")
            up = {"up": time.time(), "mode": n % len(configs), "zid": str(session.zid())}
            print(json.dumps(up), flush=True)
            stop.wait(rng.uniform(*args.up))
            print(json.dumps({"down": time.time()}), flush=True)
            token.undeclare()
            status.undeclare()
        n += 1
        stop.wait(rng.uniform(*args.down))
    return 0


if __name__ == "__main__":
    sys.exit(main())
