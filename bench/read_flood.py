"""Read flood: a peer keeps status reads in flight as fast as the daemon answers them, while a
Rider sends commands beside it; for each layout of Zenoh's threads (`bus.zenoh_threads`). Then
the same with a flood of samples: the peer puts on `rider/<login>/<id>/heartbeat` as fast as it
can (a rogue on the open profile: every such sample is a Python callback on Zenoh's thread).

The `status`, `io/**` and `axis/**` reads are answered on Zenoh's own thread (they never block),
so with one Zenoh thread a flood of them shares that thread with every command's receipt and
reply and every publication's send. Three daemons (1 thread, the default; 2; Zenoh's own
layout, `0`) are flooded in turn, in rounds, by one flooder process (its own Zenoh session,
`WINDOW` gets in flight); meanwhile this process sends sequential `check/home` gets 2 ms apart.
Per phase: the reads the flooder got answered (or the samples it put), the commands' round
trips, and the daemon's cycle counters (`diag/reset` before, `diag/cycle` after).
"""

from __future__ import annotations

import contextlib
import itertools
import sys
import tempfile
import time
from pathlib import Path

import zenoh

from bench import common
from bench.common import ms
from bench.daemon import Tuning, bench_daemon
from ride_machine.rider.client import zenoh_config as rider_zenoh_config
from tests.procs import Daemon

PERIOD_S = 0.010
LAYOUTS = (1, 2, 0)
"""`bus.zenoh_threads` of each daemon (0: Zenoh's own layout, six threads)."""
WINDOW = 32
"""Status gets the flooder keeps in flight."""
KINDS = ("reads", "samples")
"""What the flooder sends: status gets (`WINDOW` in flight), or heartbeat samples."""
SAMPLE_KEY = "rider/flood/0000/heartbeat"
"""Where the sample flood goes: a made-up Rider's heartbeat, which every daemon subscribes to."""
PUT_BATCH = 1000
COMMAND_GAP_S = 0.002
GET_TIMEOUT_S = 2.0
WARM_UP_S = 30.0
"""How long a session may take to meet its machine on a loaded host."""


def flooder(connect: str, zenoh_config: Path, key: str) -> int:
    """Reads `run <seconds> <kind>` lines; floods for that long (`reads`: gets of `key`;
    `samples`: puts on `SAMPLE_KEY`), answering `result <reads answered or samples put>`."""
    with zenoh.open(rider_zenoh_config(zenoh_config, connect=[connect])) as session:
        key_expr = session.declare_keyexpr(key)
        pub = session.declare_publisher(SAMPLE_KEY, congestion_control=zenoh.CongestionControl.DROP)
        print("ready", flush=True)
        for seconds, kind in common.run_lines():
            end = time.monotonic() + float(seconds)
            count = 0
            while time.monotonic() < end:
                if kind == "samples":
                    for _ in range(PUT_BATCH):
                        pub.put(b"beat")
                    count += PUT_BATCH
                    continue
                pending = [session.get(key_expr, timeout=GET_TIMEOUT_S) for _ in range(WINDOW)]
                for replies in pending:
                    count += sum(1 for r in replies if r.ok is not None)
            print(f"result {count}", flush=True)
    return 0


def _label(threads: int) -> str:
    return "Zenoh's own (0: six threads)" if threads == 0 else str(threads)


def _commands(
    session: zenoh.Session, key: str, seconds: float, ids: itertools.count[int]
) -> list[float]:
    """Sequential `check/home` gets, `COMMAND_GAP_S` apart, for `seconds`: their round trips."""
    out: list[float] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        payload = common.command_request(f"rf-{next(ids)}")
        t0 = time.perf_counter()
        replies = list(session.get(key, payload=payload, timeout=GET_TIMEOUT_S))
        out.append(time.perf_counter() - t0)
        common.only_reply(replies, key)
        time.sleep(COMMAND_GAP_S)
    return out


def run(opts: common.Options) -> common.Section:
    seconds = opts.pick(1.0, 6.0, 15.0)
    rounds = opts.pick(1, 2, 3)
    section = common.Section("read_flood", "10. Read flood and Zenoh's threads")
    phases = [(kind, n) for kind in KINDS for n in LAYOUTS]
    rtts: dict[tuple[str, int], list[float]] = {p: [] for p in phases}
    sent: dict[tuple[str, int], int] = dict.fromkeys(phases, 0)
    jitter: dict[tuple[str, int], list[float]] = {p: [] for p in phases}
    overruns: dict[tuple[str, int], int] = dict.fromkeys(phases, 0)
    flooded_s: dict[tuple[str, int], float] = dict.fromkeys(phases, 0.0)
    ids = itertools.count()
    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-rf-")))
        daemons: dict[int, Daemon] = {
            n: stack.enter_context(
                bench_daemon(PERIOD_S, Tuning(zenoh_threads=n), machine_id=f"rf{n}")
            )
            for n in LAYOUTS
        }
        floods: dict[int, common.Child] = {}
        for n, daemon in daemons.items():
            floods[n] = common.start_module(
                stack,
                tmp / f"flooder-{n}.log",
                "bench.read_flood",
                "flooder",
                "--connect",
                daemon.endpoint,
                "--zenoh-config",
                daemon.zenoh_config,
                "--key",
                f"machine/{daemon.machine_id}/status",
                stdin=True,
            )
        for flood in floods.values():
            flood.expect("ready")
        riders = {n: stack.enter_context(d.rider(supervise=False)) for n, d in daemons.items()}
        for rider in riders.values():
            # Warm-up: the session has met its machine. Through the Rider, which asks again
            # when an answer comes back empty (the machine's queryables not yet declared to
            # this session: seen on a loaded host as "expected one reply, got 0").
            rider.status(timeout=WARM_UP_S)
            rider.check_home()
            _commands(rider.session, f"{rider.base}/cmd/check/home", 0.2, ids)
        for r in range(rounds):
            for kind, n in phases if r % 2 == 0 else phases[::-1]:
                rider = riders[n]
                rider.diag(reset=True)
                t0 = time.monotonic()
                floods[n].send(f"run {seconds} {kind}")
                phase = (kind, n)
                rtts[phase] += _commands(
                    rider.session, f"{rider.base}/cmd/check/home", seconds, ids
                )
                sent[phase] += int(floods[n].expect("result", timeout=seconds + 30.0))
                flooded_s[phase] += time.monotonic() - t0
                diag = rider.diag()
                jitter[phase].append(diag.jitter.p99)
                overruns[phase] += diag.overruns
    titles = {
        "reads": (
            f"A flooder keeping {WINDOW} `status` gets in flight, {rounds} × {seconds:g} s per"
            f" layout (interleaved), commands 2 ms apart beside it; daemon loop at"
            f" {PERIOD_S * 1e3:g} ms",
            "reads/s answered",
        ),
        "samples": (
            f"A flooder putting samples on `{SAMPLE_KEY}` as fast as it can (congestion control"
            f" `DROP`), {rounds} × {seconds:g} s per layout (interleaved with the read flood),"
            f" commands 2 ms apart beside it; daemon loop at {PERIOD_S * 1e3:g} ms",
            "samples/s put",
        ),
    }
    for kind in KINDS:
        title, rate = titles[kind]
        table = common.Table(
            title,
            [
                "Zenoh threads (bus.zenoh_threads)",
                rate,
                "commands",
                "command p50 ms",
                "command p99 ms",
                "scan jitter p99 ms (worst phase)",
                "overruns",
            ],
        )
        for n in LAYOUTS:
            phase = (kind, n)
            d = common.Dist.of(rtts[phase])
            table.add(
                _label(n),
                f"{sent[phase] / flooded_s[phase]:,.0f}",
                len(rtts[phase]),
                ms(d.p50),
                ms(d.p99),
                ms(max(jitter[phase])),
                overruns[phase],
            )
        section.tables.append(table)
    default = LAYOUTS[0]
    for kind, what in (("reads", "the flood"), ("samples", "the sample flood")):
        phase = (kind, default)
        section.targets.append(
            common.Target(
                f"overruns at {PERIOD_S * 1e3:g} ms under {what}, {default} Zenoh thread (default)",
                "0",
                f"{overruns[phase]} in {flooded_s[phase]:.0f} s",
                overruns[phase] == 0,
            )
        )
    section.targets.append(
        common.Target.at_most(
            f"command p99 beside the flood, {default} Zenoh thread (within one period)",
            common.Dist.of(rtts[("reads", default)]).p99,
            PERIOD_S,
            lambda x: f"{ms(x)} ms",
        )
    )
    section.notes.append(
        "The reads and the commands are answered on Zenoh's thread(s) (a command that finds"
        " the loop's lock taken waits on a thread of its own). With one Zenoh thread the flood"
        " and the commands share it: the flooder gets more reads answered, and a command beside"
        " it waits longer. The scan loop runs on its own thread either way; its jitter and"
        " overruns say what the flood cost it."
    )
    samples = common.Dist.of(rtts[("samples", default)]).p50
    others = ", ".join(
        f"{ms(common.Dist.of(rtts[('samples', n)]).p50)} ms with {_label(n)}"
        for n in LAYOUTS
        if n != default
    )
    section.notes.append(
        f"The sample flood: every heartbeat sample is a Python callback on Zenoh's thread (one"
        f" dict write); with one thread the flood's samples and a command's query wait for the"
        f" same worker: a command took {ms(samples)} ms at the median with {default} thread,"
        f" {others}. Only a peer on the bus can do this: the ACL profiles keep a rogue off it"
        " (docs/security.md row 19)."
    )
    return section


def flooder_main(argv: list[str]) -> int:
    parser = common.child_parser("bench.read_flood flooder")
    parser.add_argument("--key", required=True)
    args = parser.parse_args(argv)
    return flooder(args.connect, args.zenoh_config, args.key)


def main(argv: list[str] | None = None) -> int:
    children = {"flooder": flooder_main}
    return common.main_or_child("bench.read_flood", __doc__ or "", run, argv, children)


if __name__ == "__main__":
    sys.exit(main())
