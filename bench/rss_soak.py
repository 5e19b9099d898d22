"""RSS soak: does the daemon's resident memory stay flat, idle and with Riders coming and going?

`python -m bench.rss_soak [--minutes 30] [--every 0.2]` runs side by side, for the whole time:
- a daemon at 10 ms with no Rider (its defaults);
- a daemon at 10 ms with Rider churn: a Rider connects, reads the status and disconnects,
  waits `--every` seconds, and again; with its malloc arenas capped (`loop.malloc_arenas = 2`,
  service/supervision/malloc.py);
- the same with glibc's default malloc arenas (8 per core): the daemon's default;
- a bare zenoh-python echo under the same churn (a session, a liveliness token, one get): the
  floor of what Zenoh itself keeps per connect;
- a daemon with rides (the fast simulator, its defaults otherwise): an operator Rider homes
  and runs a session, back to back, so that its history process writes all the while;
- the same with the history written on a thread of the daemon (`[events] process = false`).
RSS (/proc/<pid>/status) and the malloc arenas (from /proc/<pid>/maps) of each process are
sampled every few seconds, a daemon's with its history process's; growth is taken after the
warm-up (the first third of the run, at most 5 minutes). Issue 59's footprint is judged on the
riding daemons: the daemon and its history process together at most 70 MB at every sample.
Results are printed and written to the `rss_soak` section of BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from bench.common import (
    RESULTS,
    Child,
    Section,
    Table,
    Target,
    children,
    command_line,
    growth_per_hour,
    measure_and_save,
    python_module,
    rss_bytes,
    soak_parser,
    tenths,
)
from bench.soak import Rides, rides_worker
from ride_machine.rider.client import RiderError
from ride_machine.rider.client import zenoh_config as rider_zenoh_config
from ride_machine.service.supervision.malloc import ARENA_ENV, MALLOC_ARENAS, TUNABLES_ENV
from tests.integration.support import fast_args
from tests.procs import Daemon, free_port, malloc_arenas, start_daemon, write_zenoh_config
from tests.reliability.support import environ

SAMPLE_EVERY_S = 10.0
PROGRESS_EVERY = 30
"""Samples between progress lines on stdout (5 minutes)."""
WARMUP_MAX_S = 300.0
REPLY_TIMEOUT_S = 2.0
STEP_JOIN_S = 40.0
"""How long the end waits for a worker: a ride in progress ends its step first (bench.soak's
step timeout is 30 s)."""
FLAT_MIB_PER_H = 1.0
"""The issue's "flat": at most this slope over the second half (0.5 MiB in a 30-minute run's)."""
JUDGED_MINUTES = 10
"""Shorter runs report the slopes but judge nothing (a slope over seconds is start-up)."""
ECHO_KEY = "bench/echo"
PAIR_MAX = 70 * 10**6
"""Issue 59: a daemon and its history process together, after an hour of rides (66.8 MiB)."""
NO_ESTOPS = float("inf")
"""The rides here press no E-stop (bench.soak does): a ride after a ride."""


@dataclass(frozen=True)
class RssOptions:
    minutes: float = 30.0
    every_s: float = 0.2
    out: Path | None = RESULTS


@dataclass
class Proc:
    """One process sampled through the soak, and its churn counter (None: not churned)."""

    label: str
    pid: int
    connect: Callable[[], None] | None = None
    connects: int = 0
    failures: int = 0
    rss: list[int] = field(default_factory=list)
    seen: list[int] = field(default_factory=list)
    """`connects` at each sample."""
    arenas: int = 0
    rides: Rides | None = None
    """The rides run on it (None: none)."""
    daemon: Daemon | None = None
    """The daemon the rides run on."""
    own: list[int] = field(default_factory=list)
    """Its own RSS at each sample, without its history process (`rss` has both)."""


def _rider_churn(daemon: Daemon) -> Callable[[], None]:
    def connect() -> None:
        with daemon.rider(timeout=REPLY_TIMEOUT_S, retries=0) as rider:
            rider.status()

    return connect


def _echo_churn(endpoint: str, zenoh_config: Path) -> Callable[[], None]:
    def connect() -> None:
        conf = rider_zenoh_config(zenoh_config, connect=[endpoint])
        with zenoh.open(conf) as session:
            token = session.liveliness().declare_token(f"rider/anonymous/{session.zid()}/alive")
            if not list(session.get(ECHO_KEY, payload=b"x", timeout=REPLY_TIMEOUT_S)):
                raise RiderError("no reply from the echo")
            token.undeclare()  # type: ignore[no-untyped-call]

    return connect


def churn(proc: Proc, every_s: float, stop: threading.Event) -> None:
    assert proc.connect is not None
    while not stop.wait(every_s):
        try:
            proc.connect()
            proc.connects += 1
        except (RiderError, zenoh.ZError):
            proc.failures += 1


def start_procs(stack: contextlib.ExitStack, tmp: Path, lifetime_s: float) -> list[Proc]:
    def daemon(name: str, config: str = "") -> Daemon:
        (tmp / name / "machine.toml").write_text(f"[loop]\n{config}")
        d = start_daemon(tmp / name, "m1", extra=["--config", str(tmp / name / "machine.toml")])
        stack.callback(d.stop)
        return d

    for name in ("idle", "churn", "churn-arenas", "echo", "rides", "rides-thread"):
        (tmp / name).mkdir()
    with environ({ARENA_ENV: None, TUNABLES_ENV: None}):  # theirs would win over the config
        idle = daemon("idle")
        churned = daemon("churn", f"malloc_arenas = {MALLOC_ARENAS}\n")
        unbounded = daemon("churn-arenas")
        riding = start_daemon(tmp / "rides", "m1", extra=fast_args(tmp / "rides"))
        stack.callback(riding.stop)
        extra = fast_args(tmp / "rides-thread")
        config = Path(extra[1])
        config.write_text(config.read_text() + "\n[events]\nprocess = false\n")
        threaded = start_daemon(tmp / "rides-thread", "m1", extra=extra)
        stack.callback(threaded.stop)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    zconf = write_zenoh_config(tmp / "echo")
    echo = Child(
        python_module(
            "bench.baselines.zenoh_echo",
            "--listen",
            endpoint,
            "--zenoh-config",
            zconf,
            "--lifetime",
            lifetime_s,
        ),
        tmp / "echo" / "echo.log",
    )
    stack.callback(echo.stop)
    echo.expect("ready")
    return [
        Proc("daemon, no Rider", idle.proc.pid),
        Proc(
            f"daemon, Rider churn, malloc_arenas = {MALLOC_ARENAS}",
            churned.proc.pid,
            _rider_churn(churned),
        ),
        Proc(
            "daemon, Rider churn, glibc's default arenas",
            unbounded.proc.pid,
            _rider_churn(unbounded),
        ),
        Proc("bare Zenoh echo, same churn", echo.pid, _echo_churn(endpoint, zconf)),
        Proc(RIDING, riding.proc.pid, rides=Rides(), daemon=riding),
        Proc(THREADED, threaded.proc.pid, rides=Rides(), daemon=threaded),
    ]


RIDING = "daemon + history process, rides"
THREADED = "daemon, rides, history on a thread (process = false)"


def soak(opts: RssOptions) -> Section:
    section = Section("rss_soak", "RSS soak (bench/rss_soak.py)")
    duration = 60.0 * opts.minutes
    sample_every = min(SAMPLE_EVERY_S, duration / 10)
    stop = threading.Event()
    times: list[float] = []
    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="rss-soak-")))
        procs = start_procs(stack, tmp, duration + 120.0)
        workers = [
            threading.Thread(target=churn, args=(p, opts.every_s, stop), name=f"churn-{i}")
            for i, p in enumerate(procs)
            if p.connect is not None
        ]
        workers += [
            threading.Thread(
                target=rides_worker, args=(p.daemon, p.rides, NO_ESTOPS, stop), name=f"rides-{i}"
            )
            for i, p in enumerate(procs)
            if p.rides is not None
        ]
        t0 = time.monotonic()
        for w in workers:
            w.start()
        try:
            while True:
                t = time.monotonic() - t0
                times.append(t)
                for p in procs:
                    p.rss.append(rss_bytes(p.pid, family=True))  # a history process too
                    p.own.append(rss_bytes(p.pid))
                    p.seen.append(p.connects)
                if t >= duration:
                    break
                if len(times) % PROGRESS_EVERY == 0:
                    print(progress(t, procs), flush=True)
                stop.wait(min(sample_every, duration - t))
        finally:
            stop.set()
            for w in workers:
                w.join(timeout=STEP_JOIN_S)
        for p in procs:
            p.arenas = malloc_arenas(p.pid)
        riding = next(p for p in procs if p.label == RIDING)
        held = holdings(riding.pid)
    warmup = min(WARMUP_MAX_S, duration / 3)
    section.tables += [
        curve_table(times, procs),
        growth_table(times, procs, warmup),
        pair_table(times, riding, held),
    ]
    section.targets += flat_targets(times, procs, opts.minutes)
    section.targets += [pair_target(p) for p in procs if p.rides is not None]
    section.notes.append(
        f"{opts.minutes:g} min; each churned process: connect, read, disconnect, then"
        f" {opts.every_s:g} s pause; RSS sampled every {sample_every:g} s. Warm-up left out of"
        f" the growth: the first {warmup / 60:.1f} min. Daemons: `machine run --sim` at 10 ms,"
        f" the defaults but `loop.malloc_arenas = {MALLOC_ARENAS}` where the row says so (the"
        f" environment's `{ARENA_ENV}` left out)."
    )
    return section


def progress(t: float, procs: list[Proc]) -> str:
    cells = ", ".join(f"{p.label} {p.rss[-1] / 2**20:.2f} MiB ({p.connects:,})" for p in procs)
    return f"minute {t / 60:.1f}: {cells}"


def curve_table(times: list[float], procs: list[Proc], rows: int = 10) -> Table:
    """RSS over time, a row per tenth of the run (and the last sample)."""
    churned = next(p for p in procs if p.connect is not None)
    t = Table(
        "RSS over time (MiB)",
        ["minute", f"connects ({churned.label})", *(p.label for p in procs)],
    )
    for i in tenths(len(times), rows):
        t.add(
            f"{times[i] / 60:.1f}",
            f"{churned.seen[i]:,}",
            *(f"{p.rss[i] / 2**20:.2f}" for p in procs),
        )
    return t


def _after(times: list[float], since: float) -> list[int]:
    return [i for i, t in enumerate(times) if t >= since] or [len(times) - 1]


def growth_table(times: list[float], procs: list[Proc], warmup: float) -> Table:
    half = (warmup + times[-1]) / 2
    steady, late = _after(times, warmup), _after(times, half)
    t = Table(
        "RSS growth after the warm-up",
        [
            "process",
            "connects",
            "after warm-up MiB",
            "end MiB",
            "growth MiB",
            "MiB/h, 2nd half",
            "KiB per connect, 2nd half",
            "malloc arenas",
        ],
    )
    for p in procs:
        first, last = steady[0], len(times) - 1
        slope = growth_per_hour([times[i] for i in late], [p.rss[i] for i in late])
        n = p.seen[last] - p.seen[late[0]]
        per = (p.rss[last] - p.rss[late[0]]) / 1024 / n if n else None
        t.add(
            p.label,
            f"{p.connects:,}" + (f" ({p.failures} failed)" if p.failures else ""),
            f"{p.rss[first] / 2**20:.2f}",
            f"{p.rss[last] / 2**20:.2f}",
            f"{(p.rss[last] - p.rss[first]) / 2**20:+.2f}",
            f"{slope / 2**20:+.2f}",
            "—" if per is None else f"{per:+.2f}",
            p.arenas,
        )
    t.note = (
        "MiB/h: least-squares slope of the samples in the second half after the warm-up;"
        " KiB per connect: RSS change over the connects in that half; malloc arenas at the"
        " end (glibc heaps in /proc/<pid>/maps, the main one included)"
    )
    return t


def flat_targets(times: list[float], procs: list[Proc], minutes: float) -> list[Target]:
    warmup = min(WARMUP_MAX_S, 60.0 * minutes / 3)
    late = _after(times, (warmup + times[-1]) / 2)
    targets = []
    for p in [*procs[:2], *(p for p in procs if p.rides is not None)]:
        what = f"RSS slope, {p.label} (2nd half)"
        if minutes < JUDGED_MINUTES:
            goal = f"≤ {FLAT_MIB_PER_H:.2f} MiB/h"
            targets.append(Target(what, goal, "—", None, f"judged on ≥ {JUDGED_MINUTES} min"))
            continue
        slope = growth_per_hour([times[i] for i in late], [p.rss[i] for i in late]) / 2**20
        targets.append(Target.at_most(what, slope, FLAT_MIB_PER_H, lambda v: f"{v:.2f} MiB/h"))
    return targets


def holdings(pid: int) -> dict[str, dict[str, int]]:
    """What the daemon `pid` and its history process hold, by kind (kB of `smaps_rollup`)."""
    out: dict[str, dict[str, int]] = {}
    for label, each in [("daemon", pid), *(("history process", c) for c in children(pid))]:
        fields: dict[str, int] = {}
        for name in ("status", "smaps_rollup"):
            with contextlib.suppress(OSError), open(f"/proc/{each}/{name}") as fh:
                for line in fh:
                    key, _, value = line.partition(":")
                    if value.strip().endswith("kB"):
                        fields[key] = int(value.split()[0])
        out[label] = fields
    return out


def pair_table(times: list[float], p: Proc, held: dict[str, dict[str, int]]) -> Table:
    """The riding daemon and its history process: each one's RSS, and what they hold at the
    end (files mapped: the interpreter, Zenoh's and pydantic's libraries; anonymous: the
    Python objects and the malloc heaps)."""
    assert p.rides is not None
    history = [both - own for both, own in zip(p.rss, p.own, strict=True)]
    t = Table(
        f"{RIDING}: each process (MiB)",
        ["", "daemon", "history process", "together"],
    )
    t.add("at start", *(f"{v[0] / 2**20:.2f}" for v in (p.own, history, p.rss)))
    t.add("at the end", *(f"{v[-1] / 2**20:.2f}" for v in (p.own, history, p.rss)))
    t.add("most", *(f"{max(v) / 2**20:.2f}" for v in (p.own, history, p.rss)))
    for kind, key in (("files mapped", "RssFile"), ("anonymous", "RssAnon"), ("PSS", "Pss")):
        cells = [held.get(who, {}).get(key) for who in ("daemon", "history process")]
        if None not in cells:
            total = sum(c or 0 for c in cells)
            t.add(f"at the end: {kind}", *(f"{(c or 0) / 1024:.2f}" for c in [*cells, total]))
    rides = p.rides
    faults = ", ".join(f"{k} {n}" for k, n in rides.faults.items()) or "none"
    t.note = (
        f"{rides.done:,} rides (home, then a session of a tilt and 3 revolutions) in"
        f" {times[-1] / 60:.1f} min; faults: {faults}; errors: {len(rides.errors)}."
        " RSS counts a library's pages in each process that maps it; PSS shares them out."
    )
    return t


def pair_target(p: Proc) -> Target:
    return Target.at_most(
        f"RSS, {p.label} (most of any sample)",
        max(p.rss),
        PAIR_MAX,
        lambda v: f"{v / 2**20:.1f} MiB",
    )


def build_parser() -> argparse.ArgumentParser:
    p = soak_parser("bench.rss_soak", __doc__ or "", minutes=30.0)
    p.add_argument("--every", type=float, default=0.2, help="pause between Rider connects, s")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    if not 0 < args.minutes <= 24 * 60 or args.every < 0:
        print("bench.rss_soak: need 0 < --minutes <= 1440, --every >= 0", file=sys.stderr)
        return 2
    opts = RssOptions(
        minutes=args.minutes, every_s=args.every, out=None if args.no_write else args.out
    )
    measure_and_save(lambda: soak(opts), opts.out, command_line("bench.rss_soak", argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
