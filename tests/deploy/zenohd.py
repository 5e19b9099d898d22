"""Stands in for the `zenohd` binary of the router image, with its command line (`-c FILE`).

    python -m tests.deploy.zenohd -c docker/zenohd.json5 [--cfg KEY:VALUE]...

zenohd is not installable here; the router is Zenoh's own code either way (the same release,
see test_router_is_the_zenoh_release_we_build_against). It opens one session with the config
file as it is, prints `ready <zid>`, and closes it on SIGTERM/SIGINT (exit 0).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

import zenoh


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="zenohd", description=__doc__)
    p.add_argument("-c", "--config", type=Path, required=True, help="the router's json5 config")
    p.add_argument(
        "--cfg", action="append", default=[], metavar="KEY:VALUE", help="as zenohd: one setting"
    )
    args = p.parse_args(argv)
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    conf = zenoh.Config.from_file(str(args.config))
    for setting in args.cfg:
        key, _, value = setting.partition(":")
        conf.insert_json5(key, value)
    with zenoh.open(conf) as session:
        print(f"ready {session.zid()}", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
