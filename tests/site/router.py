"""A test stand-in for `zenohd`: one Python Zenoh session opened in `router` mode.

    python -m tests.site.router --config router.json5 --listen tcp/127.0.0.1:17447 \
        [--connect tcp/127.0.0.1:7447]

zenohd is not installable here, and the router is Zenoh's own code either way: this process
only opens the session with the site's router config (docs/site.md) and holds it. It prints
one JSON line `{"ready": <zid>, "listen": [...]}` once it listens, then runs until SIGTERM /
SIGINT (it closes the session and exits 0) or SIGKILL (a router that dies).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

import zenoh


def router_config(path: Path, listen: list[str], connect: list[str] | None = None) -> zenoh.Config:
    """The router's config file with its listen (and connect) endpoints replaced; always
    `router` mode."""
    conf = zenoh.Config.from_file(str(path))
    conf.insert_json5("mode", '"router"')
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    return conf


def stop_on_signals() -> threading.Event:
    """An event SIGTERM and SIGINT set, instead of ending the process: a stand-in router then
    closes its session and exits 0."""
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return stop


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="router", description=__doc__)
    p.add_argument("--config", type=Path, required=True, help="the router's json5 config")
    p.add_argument("--listen", action="append", default=[], help="listen endpoint")
    p.add_argument("--connect", action="append", default=[], help="endpoint it dials itself")
    args = p.parse_args(argv)
    stop = stop_on_signals()
    conf = router_config(args.config, args.listen, args.connect)
    with zenoh.open(conf) as session:
        listen = json.loads(conf.get_json("listen/endpoints"))
        print(json.dumps({"ready": str(session.zid()), "listen": listen}), flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
