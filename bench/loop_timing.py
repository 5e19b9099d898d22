"""Scan loop timing at 10 ms and 1 ms, idle and under load, read from the daemon's own diag.

Under load a Rider process sends 200 commands/s and decodes every publication while the
machine runs sessions back to back. Each run resets the daemon's counters first. Two
cross-checks from outside the daemon: the cycles it ran (plus those it reports missed) against
the bench's own clock, and under load the jitter recomputed from the axis records' stamps.
Beside them, in the same run: the same `RealtimeRunner` with an empty scan (the floor), and
1 ms variants with each real-time option of the `[loop]` config.
"""

from __future__ import annotations

import contextlib
import json
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.common import (
    Child,
    CpuMeter,
    Options,
    Section,
    Table,
    Target,
    main_for,
    ms,
    python_module,
    rss_bytes,
    share,
)
from bench.daemon import Tuning, bench_daemon
from schema.diag import CycleDiag, TimingStats
from tests.procs import Daemon

LOAD_RATE = 200.0
SPIN_S = 0.0002
FIFO = 50
PIN_CPU = 1


@dataclass(frozen=True)
class Run:
    """One measured configuration."""

    period_s: float
    load: bool
    tuning: Tuning = field(default_factory=Tuning)
    bare: bool = False

    @property
    def name(self) -> str:
        what = "empty runner (floor)" if self.bare else "daemon"
        return f"{what}, {self.period_s * 1e3:g} ms, {'load' if self.load else 'idle'}"


@dataclass
class Result:
    run: Run
    seconds: float
    diag: CycleDiag
    cpu: float = float("nan")
    rss: int = 0
    expected_cycles: float = float("nan")
    counted_cycles: int = 0
    load: dict[str, Any] = field(default_factory=dict)
    watchdog_trips: int = 0


def plan(opts: Options) -> tuple[list[tuple[Run, float]], list[tuple[Run, float]]]:
    """(main runs, variants), each with its duration in seconds."""
    main_s = opts.pick(1.0, 60.0, 600.0)
    side_s = opts.pick(0.5, 10.0, 60.0)
    main = [
        (Run(0.010, False), main_s),
        (Run(0.010, True), main_s),
        (Run(0.001, False), main_s),
        (Run(0.001, True), main_s),
    ]
    variants = [
        (Run(0.010, False, bare=True), side_s),
        (Run(0.001, False, bare=True), side_s),
        (Run(0.001, False, Tuning(rt_priority=FIFO), bare=True), side_s),
        (Run(0.001, True, Tuning(gc_freeze=False)), side_s),
        (Run(0.001, True, Tuning(spin_s=SPIN_S)), side_s),
        (Run(0.001, True, Tuning(cpu=PIN_CPU)), side_s),
        (Run(0.001, True, Tuning(rt_priority=FIFO)), side_s),
        (Run(0.001, True, Tuning(spin_s=SPIN_S, cpu=PIN_CPU, rt_priority=FIFO)), side_s),
    ]
    if opts.quick:
        # One of each code path: idle, load with motion, the floor, the tuned daemon.
        main = [main[0], main[3]]
        variants = variants[1:2] + variants[-1:]
    return main, variants


def measure_daemon(run: Run, seconds: float, tmp: Path) -> Result:
    with contextlib.ExitStack() as stack:
        daemon: Daemon = stack.enter_context(
            bench_daemon(run.period_s, run.tuning, calibrated=run.load)
        )
        rider = stack.enter_context(daemon.rider(supervise=False))
        load: Child | None = None
        if run.load:
            load = Child(
                python_module(
                    "bench.load",
                    "paced",
                    "--connect",
                    daemon.endpoint,
                    "--zenoh-config",
                    daemon.zenoh_config,
                    "--period",
                    run.period_s,
                    "--rate",
                    LOAD_RATE,
                    "--duration",
                    seconds,
                    "--motion",
                ),
                tmp / "load.log",
            )
            stack.callback(load.stop)
            load.expect("ready", timeout=60.0)
        cpu = CpuMeter(daemon.proc.pid)
        before = rider.diag(reset=True)
        t0 = time.monotonic()
        cpu.start()
        time.sleep(seconds)
        after = rider.diag()
        elapsed = time.monotonic() - t0
        result = Result(run, elapsed, after, cpu.percent(), rss_bytes(daemon.proc.pid))
        result.expected_cycles = elapsed / run.period_s
        result.counted_cycles = after.cycles - before.cycles
        if load is not None:
            result.load = json.loads(load.expect("result", timeout=seconds + 30.0))
        result.watchdog_trips = daemon.log().count("event=watchdog_trip")
        return result


def measure_bare(run: Run, seconds: float, tmp: Path) -> Result:
    t = run.tuning
    args: list[object] = ["--period", run.period_s, "--duration", seconds]
    if t.spin_s:
        args += ["--spin", t.spin_s]
    if t.cpu is not None:
        args += ["--cpu", t.cpu]
    if t.rt_priority is not None:
        args += ["--rt-priority", t.rt_priority]
    child = Child(python_module("bench.baselines.bare_loop", *args), tmp / "bare.log")
    try:
        child.expect("ready")
        cpu = CpuMeter(child.pid)
        cpu.start()
        diag = CycleDiag.model_validate(
            json.loads(child.expect("result", timeout=seconds + 10.0)), strict=False
        )
        return Result(run, seconds, diag, cpu.percent(), 0, seconds / run.period_s, diag.cycles)
    finally:
        child.stop()


def measure(run: Run, seconds: float) -> Result:
    with tempfile.TemporaryDirectory(prefix="bench-loop-") as tmp:
        if run.bare:
            return measure_bare(run, seconds, Path(tmp))
        return measure_daemon(run, seconds, Path(tmp))


def _stats_cells(s: TimingStats) -> list[str]:
    return [ms(s.p50), ms(s.p99), ms(s.max)]


def timing_table(title: str, results: list[Result]) -> Table:
    table = Table(
        title,
        [
            "run",
            "tuning",
            "s",
            "cycles",
            "jitter p50",
            "jitter p99",
            "jitter max",
            "p99 of period",
            "exec p50",
            "exec p99",
            "exec max",
            "overruns",
            "missed",
            "CPU %",
        ],
        note="times in ms; jitter = how late the scan started after its deadline;"
        " exec = scan execution time; CPU % of one core for the whole process",
    )
    for r in results:
        d = r.diag
        table.add(
            r.run.name,
            r.run.tuning.label(),
            f"{r.seconds:.0f}",
            d.cycles if r.run.bare else r.counted_cycles,
            *_stats_cells(d.jitter),
            share(d.jitter.p99, r.run.period_s),
            *_stats_cells(d.execution),
            d.overruns,
            d.missed_cycles,
            f"{r.cpu:.1f}",
        )
    return table


def crosscheck_table(results: list[Result]) -> Table:
    table = Table(
        "Cross-checks from outside the daemon",
        [
            "run",
            "cycles expected (bench clock)",
            "cycles run + reported missed",
            "axis-stamp jitter p50 / p99 / max (ms)",
            "load: commands ok / sent",
            "load: RTT p50 / p99 (ms)",
            "publications decoded",
            "watchdog trips",
            "faults seen by the load Rider",
        ],
        note="axis-stamp jitter: each axis record's stamp against the cycle grid, spread above"
        " the earliest (only while the axes move)",
    )
    for r in results:
        if r.run.bare:
            continue
        load = r.load
        jit = "—"
        if load.get("axis_jitter"):
            j = max(load["axis_jitter"].values(), key=lambda x: x["n"])
            jit = f"{ms(j['p50'])} / {ms(j['p99'])} / {ms(j['max'])}"
        table.add(
            f"{r.run.name} ({r.run.tuning.label()})",
            f"{r.expected_cycles:.0f}",
            r.counted_cycles + r.diag.missed_cycles,
            jit,
            f"{load['sent'] - load['errors']} / {load['sent']}" if load else "—",
            f"{ms(load['rtt']['p50'])} / {ms(load['rtt']['p99'])}" if load else "—",
            sum(load["samples"].values()) if load else "—",
            r.watchdog_trips,
            _counted(load["faults"]) if load else "—",
        )
    return table


def _counted(items: list[str]) -> str:
    return ", ".join(f"{k} ×{n}" for k, n in Counter(items).items()) or "none"


def targets(results: list[Result]) -> list[Target]:
    out = []
    for r in results:
        limit = 0.05 if r.run.period_s >= 0.010 else 0.20
        out.append(
            Target.at_most(
                f"p99 jitter, {r.run.name}",
                r.diag.jitter.p99,
                limit * r.run.period_s,
                lambda x: f"{ms(x)} ms",
            )
        )
    for r in results:
        if r.run.period_s >= 0.010:
            out.append(
                Target(
                    f"overruns, {r.run.name}",
                    "0",
                    str(r.diag.overruns),
                    r.diag.overruns == 0,
                    "" if r.diag.overruns == 0 else f"{r.diag.overruns} overruns",
                )
            )
    return out


def run(opts: Options) -> Section:
    main, variants = plan(opts)
    section = Section("loop_timing", "2. Scan loop timing")
    main_results = [measure(r, s) for r, s in main]
    side_results = [measure(r, s) for r, s in variants]
    section.tables.append(timing_table("Main runs (project defaults)", main_results))
    section.tables.append(
        timing_table("Side by side at 1 ms: the floor and each real-time option", side_results)
    )
    section.tables.append(crosscheck_table(main_results + side_results))
    section.targets += targets(main_results)
    section.notes.append(
        f"Load: a Rider process sending {LOAD_RATE:g} `check/home` commands/s (sequential, on an"
        " absolute schedule) and decoding every status / IO / axis / diag publication, while"
        " the machine runs the default session back to back."
    )
    section.notes.append(
        "Percentiles come from the daemon's diag over the whole run (window 100,000 cycles);"
        " max and overruns since the reset at the start of the run."
    )
    section.notes.append(
        f"Real-time options: `spin_s` = {SPIN_S * 1e3:g} ms busy-wait before each deadline,"
        f" `cpu` = {PIN_CPU} (scan thread pinned), `rt_priority` = {FIFO} (SCHED_FIFO for the"
        " scan thread), `gc_freeze` (on by default)."
    )
    return section


def main(argv: list[str] | None = None) -> int:
    return main_for("bench.loop_timing", __doc__ or "", run, argv)


if __name__ == "__main__":
    sys.exit(main())
