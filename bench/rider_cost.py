"""The Rider's own cost per call: the client CPU a `Rider` method spends over a raw Zenoh get of
the same request, measured in the client's process against one daemon.

Each pair asks the same daemon for the same thing through the same Zenoh session: the baseline is
a bare `session.get` on the Rider's declared key expression with the Rider's own options
(encoding, attachment, consolidation) and a request of the same shape, whose reply is read as
bytes and not decoded; the other is the Rider's method (request built, reply validated into its
model, the replier checked). Batches of each alternate, round by round. CPU is counted for the
calling thread (`time.thread_time`: the Rider's own Python and Zenoh's work on that thread) and
for the whole process (`time.process_time`: also Zenoh's runtime threads, the same for both
and noisier); on a shared host CPU per call is steadier than wall time.
"""

from __future__ import annotations

import itertools
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import msgpack
import zenoh

from bench.common import Options, Section, Table, Target, main_for, only_reply
from bench.daemon import bench_daemon
from ride_machine.rider.client import Rider

GOAL_US = 25.0
"""Issue 18: a Rider command costs its client at most this much CPU over the raw get."""

Call = Callable[[], object]


@dataclass
class Costs:
    """Per-call medians over the rounds, in microseconds."""

    thread: float
    process: float
    wall: float


def _raw_calls(rider: Rider) -> dict[str, Call]:
    """Bare gets of what `check_home` and `status` ask, as the Rider's session asks them."""
    session = rider.session
    ids = itertools.count()
    encoding = zenoh.Encoding("application/msgpack")
    attachment = f"rider={rider.rider_id}".encode()
    everyone = zenoh.ConsolidationMode.NONE
    cmd_key = session.declare_keyexpr(f"{rider.base}/cmd/check/home")
    status_key = session.declare_keyexpr(f"{rider.base}/status")

    def raw_command() -> bytes:
        request = {
            "transaction_id": f"raw-{next(ids)}",
            "timecode": time.time(),
            "rider": None,
            "valid_for": 4.0,
        }
        replies = list(
            session.get(
                cmd_key,
                payload=msgpack.packb(request),
                encoding=encoding,
                attachment=attachment,
                timeout=rider.timeout,
                consolidation=everyone,
            )
        )
        return only_reply(replies, "check/home")

    def raw_status() -> bytes:
        replies = list(session.get(status_key, timeout=rider.timeout, consolidation=everyone))
        return only_reply(replies, "status")

    return {"check/home": raw_command, "status": raw_status}


def _measure(
    calls: dict[str, Callable[[], object]], rounds: int, per_round: int
) -> dict[str, Costs]:
    samples: dict[str, list[tuple[float, float, float]]] = {name: [] for name in calls}
    names = list(calls)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            fn = calls[name]
            thread, process, wall = time.thread_time(), time.process_time(), time.perf_counter()
            for _ in range(per_round):
                fn()
            samples[name].append(
                (
                    (time.thread_time() - thread) / per_round * 1e6,
                    (time.process_time() - process) / per_round * 1e6,
                    (time.perf_counter() - wall) / per_round * 1e6,
                )
            )
    return {
        name: Costs(*(statistics.median(s[i] for s in rows) for i in range(3)))
        for name, rows in samples.items()
    }


def run(opts: Options) -> Section:
    section = Section("rider_cost", "9. The Rider's own cost per call")
    rounds = opts.pick(2, 12, 30)
    per_round = opts.pick(50, 500, 500)
    warmup = opts.pick(50, 500, 1000)
    with bench_daemon() as daemon, daemon.rider(supervise=False) as rider:
        raw = _raw_calls(rider)
        pairs: dict[str, tuple[Call, str, Call]] = {
            "check/home": (raw["check/home"], "Rider.check_home()", rider.check_home),
            "status": (raw["status"], "Rider.status()", rider.status),
        }
        calls: dict[str, Call] = {}
        for what, (raw_call, label, rider_call) in pairs.items():
            calls[f"raw get of {what}"] = raw_call
            calls[label] = rider_call
        for fn in calls.values():
            for _ in range(warmup):
                fn()
        costs = _measure(calls, rounds, per_round)
    table = Table(
        f"Client CPU and wall time per call, medians of {rounds} alternated batches of"
        f" {per_round}; daemon loop at 10 ms, simulator",
        ["call", "thread CPU µs", "process CPU µs", "wall µs", "thread CPU over raw µs"],
    )
    over: dict[str, Costs] = {}
    for what, (_, label, _) in pairs.items():
        base, mine = costs[f"raw get of {what}"], costs[label]
        over[what] = Costs(
            mine.thread - base.thread, mine.process - base.process, mine.wall - base.wall
        )
        table.add(f"raw get of {what} (baseline)", *_cells(base), "")
        table.add(label, *_cells(mine), f"{over[what].thread:.1f}")
    section.tables.append(table)

    def fmt(x: float) -> str:
        return f"{x:.1f} µs"

    command = over["check/home"]
    section.targets.append(
        Target.at_most(
            "Rider.check_home() thread CPU over the raw get", command.thread, GOAL_US, fmt
        )
    )
    section.targets.append(
        Target.at_most(
            "Rider.check_home() process CPU over the raw get", command.process, GOAL_US, fmt
        )
    )
    section.notes.append(
        "Thread CPU: the calling thread's (the Rider's Python plus Zenoh's send and wait on that"
        " thread). Process CPU also counts Zenoh's runtime threads, which do the same work for"
        f" both calls: its difference is the same cost plus noise ({command.process:.1f} µs"
        f" here against {command.thread:.1f} µs on the thread)."
    )
    section.notes.append(
        f"Wall time per call, Rider.check_home() over the raw get: {command.wall:.1f} µs"
        " (batch means; the daemon's share of a round trip is in section 1)."
    )
    return section


def _cells(c: Costs) -> tuple[str, str, str]:
    return f"{c.thread:.1f}", f"{c.process:.1f}", f"{c.wall:.1f}"


if __name__ == "__main__":
    sys.exit(main_for("bench.rider_cost", __doc__ or "", run))
