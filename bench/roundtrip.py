"""Command round trip, Rider process → daemon process over tcp/127.0.0.1, beside its baselines.

Sequential `check/home` commands to a daemon scanning at 10 ms, interleaved in rounds with a
bare zenoh-python echo queryable, gRPC unary over a Unix socket and a raw UDP echo, each in a
process of its own, so all of them see the same machine noise.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from bench import common
from bench.baselines.udp_echo import UdpClient
from bench.common import ms, share
from bench.daemon import Tuning, bench_daemon, pinnable_cpu
from ride_machine.rider.client import Rider, open_session
from ride_machine.rider.client import zenoh_config as rider_zenoh_config
from ride_machine.schema.codec import Format, decode
from ride_machine.schema.commands import Reply
from tests.procs import free_port

PERIOD_S = 0.010
RIDER = "daemon: Rider.check_home()"
RIDER_SIX = "daemon: Rider.check_home() from a process on Zenoh's own threads (zenoh_threads=0)"
RAW = "daemon: raw zenoh get"
RAW_BARE = "daemon without event history: raw zenoh get"
RAW_THREAD = "daemon, history on a daemon thread (events.process = false): raw zenoh get"
RAW_PINNED = "daemon on one CPU (loop.cpus): raw zenoh get"
ECHO_PINNED = "bare zenoh echo on the same CPU"
RAW_SIX = "daemon on Zenoh's own threads (bus.zenoh_threads = 0): raw zenoh get"
ECHO_ONE = "bare zenoh echo on one Zenoh thread"
ECHO = "bare zenoh echo queryable"
ECHO_DIRECT = "bare zenoh echo, direct callback"
ECHO_HANDOFF = "zenoh echo via a woken thread"
GRPC = "gRPC unary over UDS"
UDP = "raw UDP echo"
RAW_GOAL = 1.3
RIDER_GOAL = 1.4
GRPC_FACTOR = 1.5
LIKE_GOAL = 1.15
"""Issue 59: the raw get's p50 at most this times the echo's on the same Zenoh thread layout."""
GRPC_FASTER = 1.6
"""Issue 59: the Rider API's p50 at least this much faster than gRPC's."""
BURNERS = 2
BURNER_LIFETIME_S = 600.0
"""A neighbour left behind by a killed run ends by itself after this."""
LOADED = (RIDER, RAW, ECHO_ONE, ECHO, GRPC)
"""The paths measured again beside the neighbours."""


def worker(connect: str, zenoh_config: Path, threads: int, warmup: int) -> int:
    """A Rider in a process of its own, its Zenoh laid out for `threads` (`zenoh_threads`):
    answers each `run <n>` line with `result [<seconds>, ...]` of n sequential check_home()."""
    with Rider(
        "m1",
        connect=[connect],
        zenoh_config_path=zenoh_config,
        supervise=False,
        zenoh_threads=threads,
    ) as rider:
        for _ in range(warmup):
            rider.check_home()
        print("ready", flush=True)
        for (count,) in common.run_lines():
            took = []
            for _ in range(int(count)):
                t0 = time.perf_counter()
                rider.check_home()
                took.append(time.perf_counter() - t0)
            print("result " + json.dumps(took), flush=True)
    return 0


def _get_one(session: zenoh.Session, key: str, payload: bytes) -> bytes:
    replies = list(session.get(key, payload=payload, encoding=Format.MSGPACK.value, timeout=2.0))
    return common.only_reply(replies, key)


def run(opts: common.Options) -> common.Section:  # noqa: C901, PLR0912, PLR0915 - a benchmark script: setup, measure, report, in order
    count = opts.pick(300, 5000, 20000)
    warmup = opts.pick(50, 500, 1000)
    rounds = opts.pick(2, 10, 20)
    per_round = max(1, count // rounds)
    section = common.Section("roundtrip", "1. Command round trip")
    calls: dict[str, Callable[[], object]] = {}
    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-rt-")))
        daemon = stack.enter_context(bench_daemon(PERIOD_S))
        zconf = daemon.zenoh_config

        def echo_at(log: str, *extra: str) -> str:
            """A bare zenoh echo (`bench.baselines.zenoh_echo`) on a free port, ready; its
            endpoint."""
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            module = "bench.baselines.zenoh_echo"
            echo = common.start_module(
                stack, tmp / log, module, "--listen", endpoint, "--zenoh-config", zconf, *extra
            )
            echo.expect("ready")
            return endpoint

        # The same daemon with `[events] enabled = false`: what the history costs a command;
        # and with `[events] process = false`: the history on a thread of the daemon (before).
        bare = stack.enter_context(bench_daemon(PERIOD_S, events=False, machine_id="m2"))
        threaded = stack.enter_context(bench_daemon(PERIOD_S, events_thread=True, machine_id="m5"))
        # `loop.cpus`: the whole daemon on one CPU, against an echo pinned to it alike.
        pin = pinnable_cpu()
        if pin is not None:
            pinned = stack.enter_context(
                bench_daemon(PERIOD_S, Tuning(cpus=(pin,)), machine_id="m3")
            )
            pinned_echo_endpoint = echo_at("zenoh-echo-pinned.log", "--cpus", str(pin))

        # `bus.zenoh_threads = 0`: Zenoh's own six threads, as before the default became one;
        # and the echo on one Zenoh thread, as the daemon is by default.
        six = stack.enter_context(bench_daemon(PERIOD_S, Tuning(zenoh_threads=0), machine_id="m4"))
        one_echo_endpoint = echo_at("zenoh-echo-one.log", "--zenoh-threads", "1")

        echo_endpoint = echo_at("zenoh-echo.log")
        udp = common.start_module(stack, tmp / "udp-echo.log", "bench.baselines.udp_echo")
        udp_client = UdpClient(int(udp.expect("ready")))
        stack.callback(udp_client.close)
        grpc_missing = ""
        try:
            from bench.baselines.grpc_uds import GrpcClient
        except ImportError:
            grpc_missing = "grpcio is not installed (pip install -e '.[bench]'): no gRPC row"
        else:
            sock = tmp / "grpc.sock"
            grpc_server = common.start_module(
                stack, tmp / "grpc.log", "bench.baselines.grpc_uds", "--socket", sock
            )
            grpc_server.expect("ready")
            grpc_client = GrpcClient(str(sock))
            stack.callback(grpc_client.close)

        rider = stack.enter_context(daemon.rider(supervise=False))
        # The same Rider in a process on Zenoh's own six threads (`zenoh_threads=0`), as a
        # Rider ran before the twelfth pass: its calls timed in that process, a batch a round.
        six_rider = common.start_module(
            stack,
            tmp / "rider-six.log",
            "bench.roundtrip",
            "worker",
            "--connect",
            daemon.endpoint,
            "--zenoh-config",
            zconf,
            "--zenoh-threads",
            "0",
            "--warmup",
            warmup,
            stdin=True,
        )
        six_rider.expect("ready", timeout=60.0)

        def six_batch(n: int) -> list[float]:
            six_rider.send(f"run {n}")
            took: list[float] = json.loads(six_rider.expect("result", timeout=60.0))
            return took

        batches: dict[str, Callable[[int], list[float]]] = {RIDER_SIX: six_batch}
        echo_session = stack.enter_context(
            open_session(rider_zenoh_config(zconf, connect=[echo_endpoint]))
        )
        bare_session = stack.enter_context(
            open_session(
                rider_zenoh_config(bare.zenoh_config, connect=[bare.endpoint, threaded.endpoint])
            )
        )
        six_session = stack.enter_context(
            open_session(rider_zenoh_config(zconf, connect=[six.endpoint, one_echo_endpoint]))
        )
        checked = [(rider.session, cmd_key := f"{rider.base}/cmd/check/home")]
        checked.append((bare_session, bare_key := "machine/m2/cmd/check/home"))
        checked.append((bare_session, thread_key := "machine/m5/cmd/check/home"))
        checked.append((six_session, six_key := "machine/m4/cmd/check/home"))
        if pin is not None:
            pinned_session = stack.enter_context(
                open_session(
                    rider_zenoh_config(zconf, connect=[pinned.endpoint, pinned_echo_endpoint])
                )
            )
            checked.append((pinned_session, pinned_key := "machine/m3/cmd/check/home"))
        ids = itertools.count()
        echo_payload = common.command_request("echo-000000")
        calls[RIDER] = rider.check_home
        calls[RAW] = lambda: _get_one(
            rider.session, cmd_key, common.command_request(f"raw-{next(ids)}")
        )
        calls[RAW_BARE] = lambda: _get_one(
            bare_session, bare_key, common.command_request(f"bare-{next(ids)}")
        )
        calls[RAW_THREAD] = lambda: _get_one(
            bare_session, thread_key, common.command_request(f"thread-{next(ids)}")
        )
        calls[RAW_SIX] = lambda: _get_one(
            six_session, six_key, common.command_request(f"six-{next(ids)}")
        )
        calls[ECHO] = lambda: _get_one(echo_session, "bench/echo", echo_payload)
        calls[ECHO_ONE] = lambda: _get_one(six_session, "bench/echo", echo_payload)
        if pin is not None:
            calls[RAW_PINNED] = lambda: _get_one(
                pinned_session, pinned_key, common.command_request(f"pin-{next(ids)}")
            )
            calls[ECHO_PINNED] = lambda: _get_one(pinned_session, "bench/echo", echo_payload)
        calls[ECHO_DIRECT] = lambda: _get_one(echo_session, "bench/echo-direct", echo_payload)
        calls[ECHO_HANDOFF] = lambda: _get_one(echo_session, "bench/echo-handoff", echo_payload)
        if not grpc_missing:
            calls[GRPC] = lambda: grpc_client.call(echo_payload)
        calls[UDP] = lambda: udp_client.call(echo_payload)

        for session, key in checked:
            first = decode(
                Reply, _get_one(session, key, common.command_request("check")), Format.MSGPACK
            )
            if not first.success:
                raise RuntimeError(f"{key} refused: {first.error}")
        for fn in calls.values():
            for _ in range(warmup):
                fn()
        samples = _interleaved(calls, batches, rounds, per_round)
        # The same paths again beside two CPU-bound processes (issue 59: a busy box).
        near = {name: calls[name] for name in LOADED if name in calls}
        with common.burners(BURNERS, tmp, BURNER_LIFETIME_S):
            loaded = _interleaved(near, {}, rounds, per_round)

    dists = {name: common.Dist.of(s) for name, s in samples.items()}
    loaded_dists = {name: common.Dist.of(s) for name, s in loaded.items()}
    table = common.Table(
        f"Round trip, {per_round * rounds} sequential requests each after {warmup} warm-up"
        f" (interleaved in {rounds} rounds); daemon loop at {PERIOD_S * 1e3:g} ms, simulator",
        ["path", "p50 ms", "p90 ms", "p99 ms", "max ms", "p50 vs zenoh echo"],
    )
    echo_p50 = dists[ECHO].p50
    for name, d in dists.items():
        table.add(name, ms(d.p50), ms(d.p90), ms(d.p99), ms(d.max), f"{d.p50 / echo_p50:.2f}×")
    section.tables.append(table)
    section.notes.append(
        "Baselines are bare echoes doing no work; the daemon decodes and validates the request,"
        " runs the command in the Zenoh callback between two scan cycles (under the loop's lock),"
        " records it in the event history and encodes the reply."
    )
    on, off, thread = dists[RAW], dists[RAW_BARE], dists[RAW_THREAD]
    section.notes.append(
        f"With the event history (on by default, made and written by a process of its own,"
        f" service/adapters/history.py) the raw get took {ms(on.p50)} ms at the median and"
        f" {ms(on.p99)} ms at p99; with the history on a thread of the daemon"
        f" (`[events] process = false`, as before) {ms(thread.p50)} and {ms(thread.p99)} ms;"
        f" without it {ms(off.p50)} and {ms(off.p99)} ms (`{RAW_BARE}`: a second daemon with"
        " `[events] enabled = false`)."
    )
    raw, own, one = dists[RAW].p50, dists[RAW_SIX].p50, dists[ECHO_ONE].p50
    section.notes.append(
        f"Zenoh's threads: the daemons run Zenoh's five runtimes on one thread"
        f" (`bus.zenoh_threads = 1`, the default); `{RAW_SIX}` is a fourth daemon on Zenoh's"
        f" own layout (six threads): {ms(own)} ms at the median, {own / echo_p50:.2f}× the echo,"
        f" against {ms(raw)} ms. The echo gains from one thread too: `{ECHO_ONE}` took"
        f" {ms(one)} ms, and the raw get is {raw / one:.2f}× it."
    )
    if RAW_PINNED in dists:
        section.notes.append(
            f"`{RAW_PINNED}`: a third daemon with `[loop] cpus = [{pin}]` (every thread on CPU"
            f" {pin}), against the same echo pinned to CPU {pin} (`{ECHO_PINNED}`):"
            f" {dists[RAW_PINNED].p50 / dists[ECHO_PINNED].p50:.2f}× it at the median."
        )
    else:
        section.notes.append("One CPU only: no `loop.cpus` rows.")
    section.notes.append(
        "The client, this process, opens its sessions as a Rider does"
        " (`rider.client.open_session`): Zenoh on one worker thread, the Rider's default"
        " (`zenoh_threads`); every row's client gains from it alike."
    )
    six_p50 = dists[RIDER_SIX].p50
    section.notes.append(
        f"`{RIDER_SIX}`: the same Rider in a process of its own whose Zenoh keeps its own"
        f" layout: {ms(six_p50)} ms at the median against {ms(dists[RIDER].p50)} ms"
        f" ({six_p50 / dists[RIDER].p50:.2f}×)."
    )
    client = dists[RIDER].p50 - dists[RAW].p50
    section.notes.append(
        f"The Rider API adds {ms(client)} ms at the median to the raw get: the client's own"
        " work (packing the request, reading and validating the reply, checking who replied)."
    )
    section.notes.append(
        "`via a woken thread`: the echo queryable puts the query in a queue and wakes a"
        " thread waiting on an event, which replies — the daemon's hand-off without its work."
    )
    section.notes.append(
        "`direct callback`: the same echo declared with `zenoh.handlers.Callback(fn,"
        " indirect=False)`, which runs the Python callback on Zenoh's receive thread instead of"
        " handing it to a Python thread first (the default)."
    )
    if grpc_missing:
        section.notes.append(grpc_missing)
    # Issue 18: raw get ≤ 1.3× and Rider API ≤ 1.4× the bare echo, the Rider API below gRPC by
    # 1.5× or more, p99 under 10 % of the period.
    for name, goal in ((RAW, RAW_GOAL), (RIDER, RIDER_GOAL)):
        ratio = dists[name].p50 / echo_p50
        section.targets.append(
            common.Target.at_most(
                f"{name} p50 ÷ zenoh echo p50", ratio, goal, lambda x: f"{x:.2f}×"
            )
        )
    if RAW_PINNED in dists:
        ratio = dists[RAW_PINNED].p50 / dists[ECHO_PINNED].p50
        section.targets.append(
            common.Target.at_most(
                f"{RAW_PINNED} p50 ÷ {ECHO_PINNED} p50", ratio, RAW_GOAL, lambda x: f"{x:.2f}×"
            )
        )
    if GRPC in dists:
        grpc_p50 = dists[GRPC].p50
        section.targets.append(
            common.Target.at_most(
                f"{RIDER} p50 × {GRPC_FACTOR:g} (below gRPC p50 by {GRPC_FACTOR:g}×)",
                dists[RIDER].p50 * GRPC_FACTOR,
                grpc_p50,
                _ms_unit,
            )
        )
    p99 = dists[RIDER].p99
    section.targets.append(
        common.Target.at_most(f"{RIDER} p99 (< 10 % of the period)", p99, 0.1 * PERIOD_S, _ms_unit)
    )
    section.tables.append(_loaded_table(loaded_dists, per_round * rounds))
    busy = f"beside {BURNERS} CPU-bound processes"
    for where, measured in (("quiet", dists), (busy, loaded_dists)):
        section.targets += _like_for_like(where, measured)
    section.notes.append(
        f"p99 of the Rider path is {share(p99, PERIOD_S)} of the {PERIOD_S * 1e3:g} ms period."
    )
    return section


def _interleaved(
    calls: dict[str, Callable[[], object]],
    batches: dict[str, Callable[[int], list[float]]],
    rounds: int,
    per_round: int,
) -> dict[str, list[float]]:
    """Each path's round trips, s: `per_round` sequential calls of each in turn, `rounds` times
    (a batch is timed by the process that makes it)."""
    samples: dict[str, list[float]] = {name: [] for name in [*calls, *batches]}
    names = [RIDER, *batches, *(n for n in calls if n != RIDER)]
    for r in range(rounds):
        # Rotate the order each round, so no transport always follows the same neighbour.
        for name in names[r % len(names) :] + names[: r % len(names)]:
            out = samples[name]
            if name in batches:
                out += batches[name](per_round)
                continue
            fn = calls[name]
            for _ in range(per_round):
                t0 = time.perf_counter()
                fn()
                out.append(time.perf_counter() - t0)
    return samples


def _loaded_table(dists: dict[str, common.Dist], count: int) -> common.Table:
    table = common.Table(
        f"The same, beside {BURNERS} CPU-bound processes (bench/baselines/burner.py),"
        f" {count} sequential requests each, interleaved alike",
        ["path", "p50 ms", "p90 ms", "p99 ms", "max ms", f"p50 vs {ECHO_ONE}"],
    )
    one = dists[ECHO_ONE].p50
    for name, d in dists.items():
        table.add(name, ms(d.p50), ms(d.p90), ms(d.p99), ms(d.max), f"{d.p50 / one:.2f}×")
    return table


def _like_for_like(where: str, dists: dict[str, common.Dist]) -> list[common.Target]:
    """Issue 59's two: the raw get against the echo on the daemon's Zenoh thread layout (one
    thread), and the Rider API against gRPC over a Unix socket."""
    out = [
        common.Target.at_most(
            f"{where}: {RAW} p50 ÷ {ECHO_ONE} p50 (like for like)",
            dists[RAW].p50 / dists[ECHO_ONE].p50,
            LIKE_GOAL,
            lambda x: f"{x:.2f}×",
        )
    ]
    if GRPC in dists:
        out.append(
            common.Target.at_least(
                f"{where}: {GRPC} p50 ÷ {RIDER} p50",
                dists[GRPC].p50 / dists[RIDER].p50,
                GRPC_FASTER,
                lambda x: f"{x:.2f}×",
            )
        )
    return out


def _ms_unit(seconds: float) -> str:
    return f"{ms(seconds)} ms"


def worker_main(argv: list[str]) -> int:
    parser = common.child_parser("bench.roundtrip worker")
    parser.add_argument("--zenoh-threads", type=int, required=True)
    parser.add_argument("--warmup", type=int, required=True)
    args = parser.parse_args(argv)
    return worker(args.connect, args.zenoh_config, args.zenoh_threads, args.warmup)


def main(argv: list[str] | None = None) -> int:
    return common.main_or_child(
        "bench.roundtrip", __doc__ or "", run, argv, {"worker": worker_main}
    )


if __name__ == "__main__":
    sys.exit(main())
