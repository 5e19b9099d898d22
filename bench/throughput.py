"""Throughput: sequential commands per second from 1 and from 4 concurrent Riders, beside a bare
zenoh-python echo driven the same way, and the daemon's overruns meanwhile.

Each Rider is a process of its own with its own Zenoh session (so the clients do not share one
GIL), sending raw `check/home` gets back to back; the echo gets the same requests. Daemon and
echo phases alternate in rounds, so both see the same host noise. The daemon's cycle counters
are reset before and read after each of its phases (`diag/reset`, `diag/cycle`).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from bench import common
from bench.daemon import bench_daemon
from ride_machine.rider.client import Rider, open_session
from ride_machine.rider.client import zenoh_config as rider_zenoh_config
from ride_machine.schema.diag import CycleDiag
from tests.procs import free_port

PERIOD_S = 0.010
ECHO_KEY = "bench/echo"
GET_TIMEOUT_S = 2.0


# ------------------------------------------------------------------------------ worker
def worker(connect: list[str], zenoh_config: Path, name: str) -> int:
    """Reads `run <key> <seconds>` lines; answers each with `result {"count": n, "failed": f}`."""
    ids = itertools.count()
    # Opened as a Rider opens its session (`open_session`: Zenoh on one worker thread).
    with open_session(rider_zenoh_config(zenoh_config, connect=connect)) as session:
        print("ready", flush=True)
        for key, seconds_text in common.run_lines():
            seconds = float(seconds_text)
            count = failed = 0
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                payload = common.command_request(f"{name}-{next(ids)}")
                replies = list(session.get(key, payload=payload, timeout=GET_TIMEOUT_S))
                if len(replies) == 1 and replies[0].ok is not None:
                    count += 1
                else:
                    failed += 1
            print("result " + json.dumps({"count": count, "failed": failed}), flush=True)
    return 0


# ------------------------------------------------------------------------------- bench
THREAD_COLUMNS = (
    ("zenoh", "Zenoh's thread"),
    ("eventlog", "event writer"),
    ("log-writer", "log writer"),
    ("main", "scan thread"),
    (common.HISTORY, "history process"),
)
"""The daemon's threads named in the CPU table (`bench.common.thread_cpu`), and its history
process (`[events] process`, all its threads); the rest is `other`."""


@dataclass
class _Results:
    """What the phases measured: commands, failures and seconds per (target, Riders); the
    daemon's overruns and its CPU seconds by thread (`thread_cpu`) per Riders."""

    rows: dict[tuple[str, int], list[tuple[int, int, float]]] = field(default_factory=dict)
    overruns: dict[int, int] = field(default_factory=dict)
    threads: dict[int, dict[str, float]] = field(default_factory=dict)

    def daemon_phase(
        self, workers: list[common.Child], key: str, seconds: float, rider: Rider, pid: int
    ) -> None:
        riders = len(workers)
        rider.diag(reset=True)
        before = common.thread_cpu(pid)
        self.rows.setdefault(("daemon", riders), []).append(_phase(workers, key, seconds))
        after = common.thread_cpu(pid)
        spent = self.threads.setdefault(riders, {})
        for name, cpu_s in after.items():
            spent[name] = spent.get(name, 0.0) + cpu_s - before.get(name, 0.0)
        self.overruns[riders] = self.overruns.get(riders, 0) + rider.diag().overruns


def _by_thread(
    rows: dict[tuple[str, int], list[tuple[int, int, float]]],
    threads: dict[int, dict[str, float]],
) -> common.Table:
    """The daemon's CPU per command answered, by thread, over its phases."""
    table = common.Table(
        "The daemon's CPU per command by thread, µs (its phases above; `/proc/<pid>/task/*`"
        " schedstat, threads named for the OS by service/threads.py; its history process's"
        " threads as one)",
        ["Riders", "all threads", *(label for _, label in THREAD_COLUMNS), "other"],
    )
    for riders, spent in sorted(threads.items()):
        count = sum(p[0] for p in rows[("daemon", riders)])
        per = {name: cpu_s / count * 1e6 for name, cpu_s in spent.items()} if count else {}
        named = [per.get(name, 0.0) for name, _ in THREAD_COLUMNS]
        total = sum(per.values())
        table.add(riders, f"{total:.0f}", *(f"{x:.1f}" for x in named), f"{total - sum(named):.1f}")
    return table


def _phase(workers: list[common.Child], key: str, seconds: float) -> tuple[int, int, float]:
    """All workers run against `key` at once; (commands answered, failed, wall seconds)."""
    t0 = time.monotonic()
    for w in workers:
        w.send(f"run {key} {seconds}")
    count = failed = 0
    for w in workers:
        result = json.loads(w.expect("result", timeout=seconds + 3 * GET_TIMEOUT_S + 10))
        count += result["count"]
        failed += result["failed"]
    return count, failed, time.monotonic() - t0


def run(opts: common.Options) -> common.Section:
    seconds = opts.pick(0.5, 3.0, 8.0)
    rounds = opts.pick(1, 3, 3)
    section = common.Section("throughput", "8. Throughput")
    res = _Results()
    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-tp-")))
        daemon = stack.enter_context(bench_daemon(PERIOD_S))
        echo_endpoint = f"tcp/127.0.0.1:{free_port()}"
        echo = common.start_module(
            stack,
            tmp / "echo.log",
            "bench.baselines.zenoh_echo",
            "--listen",
            echo_endpoint,
            "--zenoh-config",
            daemon.zenoh_config,
        )
        echo.expect("ready")
        workers = [
            common.start_module(
                stack,
                tmp / f"worker-{i}.log",
                "bench.throughput",
                "worker",
                "--connect",
                daemon.endpoint,
                "--connect",
                echo_endpoint,
                "--zenoh-config",
                daemon.zenoh_config,
                "--name",
                f"tp{i}",
                stdin=True,
            )
            for i in range(4)
        ]
        for w in workers:
            w.expect("ready")
        rider = stack.enter_context(daemon.rider(supervise=False))
        cmd_key = f"{rider.base}/cmd/check/home"
        for w in workers:  # warm-up: every session has met both peers
            _phase([w], cmd_key, 0.2)
            _phase([w], ECHO_KEY, 0.2)
        # The floor for overruns: the runner with an empty scan, at the same period, for the
        # whole measurement (daemon and echo phases alike load the host).
        bare_s = rounds * 4 * (seconds + 0.5) + 5.0
        bare = common.start_module(
            stack,
            tmp / "bare.log",
            "bench.baselines.bare_loop",
            "--period",
            PERIOD_S,
            "--duration",
            bare_s,
        )
        bare.expect("ready")
        bare_t0 = time.monotonic()
        for r in range(rounds):
            for riders in (1, 4):
                order = [("daemon", cmd_key), ("echo", ECHO_KEY)]
                for target, key in order if r % 2 == 0 else order[::-1]:
                    if target == "daemon":
                        res.daemon_phase(workers[:riders], key, seconds, rider, daemon.proc.pid)
                    else:
                        res.rows.setdefault((target, riders), []).append(
                            _phase(workers[:riders], key, seconds)
                        )
        measured_s = time.monotonic() - bare_t0
        floor = CycleDiag.model_validate(
            json.loads(bare.expect("result", timeout=bare_s + 10.0)), strict=False
        )
    table = common.Table(
        f"Sequential `check/home` gets back to back, {rounds} × {seconds:g} s per row"
        f" (interleaved); daemon loop at {PERIOD_S * 1e3:g} ms, simulator",
        ["path", "Riders", "commands/s", "per Rider /s", "failed", "overruns", "vs echo"],
    )
    rate: dict[tuple[str, int], float] = {}
    for (target, riders), phases in res.rows.items():
        rate[(target, riders)] = sum(p[0] for p in phases) / sum(p[2] for p in phases)
    for riders in (1, 4):
        for target in ("daemon", "echo"):
            phases = res.rows[(target, riders)]
            r_s = rate[(target, riders)]
            table.add(
                "daemon: raw zenoh get" if target == "daemon" else "bare zenoh echo queryable",
                riders,
                f"{r_s:,.0f}",
                f"{r_s / riders:,.0f}",
                sum(p[1] for p in phases),
                res.overruns[riders] if target == "daemon" else "",
                f"{r_s / rate[('echo', riders)]:.2f}×",
            )
    section.tables.append(table)
    section.tables.append(_by_thread(res.rows, res.threads))
    section.notes.append(
        "Each Rider is its own process and Zenoh session on the same two cores as the daemon;"
        " the echo replies with the request and does no work, so its row is what Zenoh and the"
        " client processes allow on this host."
    )
    section.targets.append(
        common.Target(
            "1 Rider, sequential",
            "≥ 3,000 /s",
            f"{rate[('daemon', 1)]:,.0f} /s",
            rate[("daemon", 1)] >= 3000,
        )
    )
    section.targets.append(
        common.Target(
            "4 concurrent Riders",
            "≥ 5,000 /s",
            f"{rate[('daemon', 4)]:,.0f} /s",
            rate[("daemon", 4)] >= 5000,
        )
    )
    total = sum(res.overruns.values())
    daemon_s = sum(
        p[2] for (target, _), phases in res.rows.items() if target == "daemon" for p in phases
    )
    floor_s = floor.cycles * PERIOD_S
    section.targets.append(
        common.Target(
            "overruns at 10 ms meanwhile",
            "0",
            f"{total} in {daemon_s:.0f} s (empty runner: {floor.overruns} in {floor_s:.0f} s)",
            total == 0,
        )
    )
    section.notes.append(
        f"Overruns: the daemon's during its phases ({daemon_s:.0f} s); beside it for the whole"
        f" {measured_s:.0f} s (daemon and echo phases) the runner with an empty scan at the same"
        f" period (bench/baselines/bare_loop.py) had {floor.overruns} — the host's own share."
    )
    return section


def worker_main(argv: list[str]) -> int:
    parser = common.child_parser("bench.throughput worker", connect="append")
    parser.add_argument("--name", required=True)
    args = parser.parse_args(argv)
    return worker(args.connect, args.zenoh_config, args.name)


def main(argv: list[str] | None = None) -> int:
    return common.main_or_child(
        "bench.throughput", __doc__ or "", run, argv, {"worker": worker_main}
    )


if __name__ == "__main__":
    sys.exit(main())
