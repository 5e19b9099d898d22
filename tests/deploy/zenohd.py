"""Stands in for the `zenohd` binary of the router image, with its command line (`-c FILE`).

    python -m tests.deploy.zenohd -c docker/zenohd.json5 [--cfg KEY:VALUE]...

zenohd is not installable here; the router is Zenoh's own code either way (the same release,
see test_router_is_the_zenoh_release_we_build_against). Like zenohd it refuses arguments it
does not know, and logs the whole config it starts with (`Initial conf: …`, zenohd's
main.rs, at info for the target `zenohd` under `RUST_LOG`, default `z=info`). First it prints
`argv ["…", …]` (JSON) so a test sees how the arguments arrived. It opens one session with the
config, prints `ready <zid>`, and closes it on SIGTERM/SIGINT (exit 0).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import zenoh

from tests.site.router import stop_on_signals

LEVELS = ("off", "error", "warn", "info", "debug", "trace")


def enabled(target: str, level: str, rust_log: str) -> bool:
    """Whether `RUST_LOG` lets a line of `level` from `target` through (tracing's EnvFilter:
    comma-separated `[target=]level` directives; the longest matching target prefix wins)."""
    best: tuple[int, str] | None = None
    for directive in filter(None, (d.strip() for d in rust_log.split(","))):
        name, _, lvl = directive.rpartition("=")
        if target.startswith(name) and (best is None or len(name) > best[0]):
            best = (len(name), lvl.lower())
    return best is not None and LEVELS.index(level) <= LEVELS.index(best[1])


def main(argv: Sequence[str] | None = None) -> int:
    args_in = list(sys.argv[1:] if argv is None else argv)
    print(f"argv {json.dumps(args_in)}", flush=True)
    p = argparse.ArgumentParser(prog="zenohd", description=__doc__)
    p.add_argument("-c", "--config", type=Path, required=True, help="the router's json5 config")
    p.add_argument(
        "--cfg", action="append", default=[], metavar="KEY:VALUE", help="as zenohd: one setting"
    )
    args = p.parse_args(args_in)
    stop = stop_on_signals()
    conf = zenoh.Config.from_file(str(args.config))
    for setting in args.cfg:
        key, _, value = setting.partition(":")
        conf.insert_json5(key, value)
    if enabled("zenohd", "info", os.environ.get("RUST_LOG", "z=info")):
        print(f"INFO zenohd: Initial conf: {conf}", flush=True)
    with zenoh.open(conf) as session:
        print(f"ready {session.zid()}", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
