"""A bare zenoh-python echo queryable: replies with the request payload.

Three keys: `bench/echo` replies in the callback (Zenoh's default: the callback runs on a
Python thread Zenoh hands it to); `bench/echo-direct` runs the callback on Zenoh's own receive
thread (`indirect=False`); `bench/echo-handoff` does what the daemon does with a command: the
callback queues the query and wakes a thread waiting on an event, which replies.
"""

from __future__ import annotations

import argparse
import sys
import threading
from collections import deque
from pathlib import Path

import zenoh

from bench.baselines.lifetime import stop_event
from ride_machine.service.bus import use_runtime, zenoh_config
from ride_machine.service.core.scan.tuning import pin_process

KEY = "bench/echo"
DIRECT_KEY = "bench/echo-direct"
HANDOFF_KEY = "bench/echo-handoff"


def echo(query: zenoh.Query) -> None:
    payload = query.payload
    query.reply(query.key_expr, payload.to_bytes() if payload is not None else b"")


class Handoff:
    """Queries answered by a worker thread woken through an event, like the scan thread."""

    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop
        self.queue: deque[zenoh.Query] = deque()
        self.wake = threading.Event()
        self.thread = threading.Thread(target=self._run, name="handoff", daemon=True)

    def put(self, query: zenoh.Query) -> None:
        self.queue.append(query)
        self.wake.set()

    def _run(self) -> None:
        while not self.stop.is_set():
            if not self.wake.wait(0.01):
                continue
            self.wake.clear()
            while self.queue:
                query = self.queue.popleft()
                with query:  # finalises the query, so the caller's get ends at once
                    echo(query)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--listen", required=True, help="e.g. tcp/127.0.0.1:7450")
    parser.add_argument("--zenoh-config", type=Path, required=True, help="the daemon's zenoh.json5")
    parser.add_argument("--lifetime", type=float, default=600.0, help="exit after this many s")
    parser.add_argument(
        "--cpus", help="pin the echo (every thread) to these CPUs, e.g. 1 or 0,1 (`loop.cpus`)"
    )
    parser.add_argument(
        "--zenoh-threads",
        type=int,
        default=0,
        help="Zenoh's runtimes on one pool of this many threads (`bus.zenoh_threads`); 0, the"
        " default: Zenoh's own layout",
    )
    args = parser.parse_args(argv)
    if args.cpus is not None and pin_process([int(c) for c in args.cpus.split(",")]) is None:
        return 1
    use_runtime(args.zenoh_threads)
    stop = stop_event(args.lifetime)
    handoff = Handoff(stop)
    handoff.thread.start()
    # The daemon's own session config (peer, no scouting, one listen endpoint): a fair floor.
    with zenoh.open(zenoh_config(args.zenoh_config, [args.listen])) as session:
        queryables = [
            session.declare_queryable(KEY, echo),
            session.declare_queryable(DIRECT_KEY, zenoh.handlers.Callback(echo, indirect=False)),
            session.declare_queryable(HANDOFF_KEY, handoff.put),
        ]
        print(f"ready {args.listen}", flush=True)
        stop.wait()
        for queryable in queryables:
            queryable.undeclare()  # type: ignore[no-untyped-call]
    handoff.thread.join(timeout=1.0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
