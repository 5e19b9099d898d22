"""A CPU-bound neighbour: a Python process that computes without pause (a build, a batch job
on the same host), until its lifetime ends or it is stopped."""

from __future__ import annotations

import argparse
import sys

from bench.baselines.lifetime import stop_event


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lifetime", type=float, default=600.0, help="exit after this many s")
    args = parser.parse_args(argv)
    stop = stop_event(args.lifetime)
    print("ready", flush=True)
    while not stop.is_set():
        sum(range(10_000))  # ~0.1 ms of work between two looks at the stop event
    return 0


if __name__ == "__main__":
    sys.exit(main())
