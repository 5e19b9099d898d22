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
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from bench import common
from bench.common import ms, share
from bench.daemon import Tuning, bench_daemon
from ride_machine.schema.diag import CycleDiag, TimingStats
from tests.procs import Daemon

LOAD_RATE = 200.0
WATCHDOG_S = 0.030
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
    kernel_slack: bool = False
    """Empty runner only: keep the kernel's 50 µs timer slack instead of the runner's 1 µs."""
    neighbours: int = 0
    """CPU-bound processes (bench/baselines/burner.py) running beside it, one per core."""

    @property
    def name(self) -> str:
        what = "empty runner" if self.bare else "daemon"
        name = f"{what}, {self.period_s * 1e3:g} ms, {'load' if self.load else 'idle'}"
        return f"{name}, {self.neighbours} CPU-bound neighbours" if self.neighbours else name

    @property
    def label(self) -> str:
        extra = ["kernel timer slack"] if self.kernel_slack else []
        return ", ".join([*extra, self.tuning.label()]) if extra else self.tuning.label()

    @property
    def watchdog_periods(self) -> int | None:
        """Under load the watchdog waits 30 ms (its 10 ms default) so a stall on this busy
        host does not fault the machine and stop the motion the load is about."""
        return max(3, round(WATCHDOG_S / self.period_s)) if self.load else None


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
    alongside: Result | None = None
    """The empty runner that ran at the same time, at the same period: the noise of the moment."""


Groups = list[tuple[list[Run], float]]


def plan(opts: common.Options) -> tuple[list[tuple[Run, float]], Groups, Groups]:
    """(main runs, side-by-side groups, rounds beside CPU-bound neighbours), with durations;
    a group's runs run concurrently."""
    main_s = opts.pick(1.0, 60.0, 600.0)
    side_s = opts.pick(0.5, 8.0, 60.0)
    main = [
        (Run(0.010, False), main_s),
        (Run(0.010, True), main_s),
        (Run(0.001, False), main_s),
        (Run(0.001, True), main_s),
        # The same on the kernel's time slice (`loop.slice_s = 0`): the default before it.
        (Run(0.001, True, Tuning(kernel_slice=True)), main_s),
    ]
    tuned = Tuning(spin_s=SPIN_S, cpu=PIN_CPU, rt_priority=FIFO)
    side = [
        (
            [
                Run(0.001, False, bare=True),
                Run(0.001, False, bare=True, kernel_slack=True),
                Run(0.001, False, Tuning(kernel_slice=True), bare=True),
            ],
            side_s,
        ),
        ([Run(0.001, False, Tuning(rt_priority=FIFO), bare=True)], side_s),
        ([Run(0.001, True, Tuning(gc_freeze=False))], side_s),
        ([Run(0.001, True, Tuning(spin_s=SPIN_S))], side_s),
        ([Run(0.001, True, Tuning(cpu=PIN_CPU))], side_s),
        ([Run(0.001, True, Tuning(cpus=(PIN_CPU,)))], side_s),
        ([Run(0.001, True, Tuning(cpus=(PIN_CPU,), cpu=1 - PIN_CPU))], side_s),
        ([Run(0.001, True, Tuning(rt_priority=FIFO))], side_s),
        ([Run(0.001, True, tuned)], side_s),
    ]
    if opts.quick:
        # One of each code path: idle, load with motion, a bare group, the tuned daemon.
        main = [main[0], main[3]]
        side = [side[0], side[-1]]
    return main, side, neighbour_rounds(opts)


def neighbour_rounds(opts: common.Options) -> Groups:
    """The daemon at 1 ms under load with a CPU-bound process per core beside it: what
    `loop.slice_s` is for. Its own slice and the kernel's alternate, round by round."""
    cores = len(os.sched_getaffinity(0))
    mine = Run(0.001, True, neighbours=cores)
    kernel = Run(0.001, True, Tuning(kernel_slice=True), neighbours=cores)
    rounds = opts.pick(1, 3, 5)
    return [([run], opts.pick(0.5, 15.0, 60.0)) for _ in range(rounds) for run in (mine, kernel)]


def measure_daemon(run: Run, seconds: float, tmp: Path) -> Result:
    with contextlib.ExitStack() as stack:
        daemon: Daemon = stack.enter_context(
            bench_daemon(
                run.period_s,
                run.tuning,
                calibrated=run.load,
                watchdog_periods=run.watchdog_periods,
            )
        )
        rider = stack.enter_context(daemon.rider(supervise=False))
        load: common.Child | None = None
        if run.load:
            load = common.start_module(
                stack,
                tmp / "load.log",
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
            )
            load.expect("ready", timeout=60.0)
        stack.enter_context(common.burners(run.neighbours, tmp, seconds + 120.0))
        canary = BareRunner(Run(run.period_s, run.load, bare=True), seconds, tmp / "canary.log")
        stack.callback(canary.child.stop)
        cpu = common.CpuMeter(daemon.proc.pid, family=True)
        before = rider.diag(reset=True)
        t0 = time.monotonic()
        cpu.start()
        time.sleep(seconds)
        after = rider.diag()
        elapsed = time.monotonic() - t0
        result = Result(
            run, elapsed, after, cpu.percent(), common.rss_bytes(daemon.proc.pid, family=True)
        )
        result.expected_cycles = elapsed / run.period_s
        result.counted_cycles = after.cycles - before.cycles
        if load is not None:
            result.load = json.loads(load.expect("result", timeout=seconds + 30.0))
        result.watchdog_trips = daemon.log().count("event=watchdog_trip")
        result.alongside = canary.result()
        return result


class BareRunner:
    """An empty-scan `RealtimeRunner` process (bench/baselines/bare_loop.py), started at once."""

    def __init__(self, run: Run, seconds: float, log: Path) -> None:
        self.run = run
        self.seconds = seconds
        t = run.tuning
        args: list[object] = ["--period", run.period_s, "--duration", seconds]
        if t.spin_s:
            args += ["--spin", t.spin_s]
        if t.cpu is not None:
            args += ["--cpu", t.cpu]
        if t.rt_priority is not None:
            args += ["--rt-priority", t.rt_priority]
        if not t.gc_freeze:
            args.append("--no-gc-freeze")
        if run.kernel_slack:
            args.append("--kernel-timer-slack")
        if t.kernel_slice:
            args.append("--kernel-slice")
        self.child = common.Child(common.python_module("bench.baselines.bare_loop", *args), log)
        self.child.expect("ready")
        self.cpu = common.CpuMeter(self.child.pid)
        self.cpu.start()

    def result(self) -> Result:
        """Wait for its end (bounded) and read the statistics it printed."""
        text = self.child.expect("result", timeout=self.seconds + 10.0)
        cpu = self.cpu.percent()
        self.child.stop()
        diag = CycleDiag.model_validate(json.loads(text), strict=False)
        expected = self.seconds / self.run.period_s
        return Result(self.run, self.seconds, diag, cpu, 0, expected, diag.cycles)


def measure_bare_group(runs: list[Run], seconds: float, tmp: Path) -> list[Result]:
    """Empty runners side by side, at the same time, so they share the host's noise."""
    with contextlib.ExitStack() as stack:
        started = []
        for i, run in enumerate(runs):
            bare = BareRunner(run, seconds, tmp / f"bare-{i}.log")
            stack.callback(bare.child.stop)
            started.append(bare)
        return [b.result() for b in started]


def measure_group(runs: list[Run], seconds: float) -> list[Result]:
    with tempfile.TemporaryDirectory(prefix="bench-loop-") as tmp:
        if all(r.bare for r in runs):
            return measure_bare_group(runs, seconds, Path(tmp))
        return [measure_daemon(r, seconds, Path(tmp)) for r in runs]


def _stats_cells(s: TimingStats) -> list[str]:
    return [ms(s.p50), ms(s.p99), ms(s.max)]


def timing_table(title: str, results: list[Result]) -> common.Table:
    table = common.Table(
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
        _timing_row(table, r, r.run.name)
        if r.alongside is not None:
            _timing_row(table, r.alongside, "↳ empty runner alongside")
    return table


def _timing_row(table: common.Table, r: Result, name: str) -> None:
    d = r.diag
    table.add(
        name,
        r.run.label,
        f"{r.seconds:.3g}",
        d.cycles if r.run.bare else r.counted_cycles,
        *_stats_cells(d.jitter),
        share(d.jitter.p99, r.run.period_s),
        *_stats_cells(d.execution),
        d.overruns,
        d.missed_cycles,
        f"{r.cpu:.1f}",
    )


def crosscheck_table(results: list[Result]) -> common.Table:
    table = common.Table(
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
            f"{r.run.name} ({r.run.label})",
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


def neighbour_note(results: list[Result]) -> str:
    """The medians of the alternated rounds beside CPU-bound neighbours, per slice."""
    parts = []
    for kernel in (False, True):
        rs = [r for r in results if r.run.tuning.kernel_slice is kernel]
        if not rs:
            continue
        p99 = statistics.median(r.diag.jitter.p99 for r in rs)
        overruns = statistics.median(r.diag.overruns for r in rs)
        which = "on the kernel's slice" if kernel else "on its own 0.1 ms slice (the default)"
        parts.append(
            f"{which}: p99 jitter {ms(p99)} ms and {overruns:g} overruns, the median of"
            f" {len(rs)} rounds"
        )
    return (
        "Beside CPU-bound neighbours (bench/baselines/burner.py, one per core: a build or a"
        " batch job on the same host), the daemon " + "; ".join(parts) + "."
    )


def _counted(items: list[str]) -> str:
    return ", ".join(f"{k} ×{n}" for k, n in Counter(items).items()) or "none"


def targets(results: list[Result]) -> list[common.Target]:
    out = []
    for r in results:
        limit = (0.05 if r.run.period_s >= 0.010 else 0.20) * r.run.period_s
        t = common.Target.at_most(
            f"p99 jitter, {r.run.name}", r.diag.jitter.p99, limit, lambda x: f"{ms(x)} ms"
        )
        if r.alongside is not None:
            t = replace(
                t, measured=f"{t.measured} (empty runner: {ms(r.alongside.diag.jitter.p99)})"
            )
        out.append(t)
    for r in results:
        if r.run.period_s >= 0.010:
            n = r.diag.overruns
            beside = f" (empty runner: {r.alongside.diag.overruns})" if r.alongside else ""
            out.append(
                common.Target(
                    f"overruns, {r.run.name}", "0", f"{n}{beside}", n == 0, f"{n} overruns"
                )
            )
    return out


def run(opts: common.Options) -> common.Section:
    main, variants, rounds = plan(opts)
    section = common.Section("loop_timing", "2. Scan loop timing")
    main_results = [r for run, seconds in main for r in measure_group([run], seconds)]
    side_results = [r for runs, seconds in variants for r in measure_group(runs, seconds)]
    crowded = [r for runs, seconds in rounds for r in measure_group(runs, seconds)]
    section.tables.append(timing_table("Main runs (project defaults)", main_results))
    section.tables.append(timing_table("Side by side at 1 ms: each real-time option", side_results))
    section.tables.append(
        timing_table(
            "Beside a CPU-bound process per core, 1 ms, load: the daemon's time slice"
            " (`loop.slice_s`) and the kernel's, rounds alternated",
            crowded,
        )
    )
    section.notes.append(neighbour_note(crowded))
    section.tables.append(crosscheck_table(main_results + side_results + crowded))
    section.targets += targets([r for r in main_results if r.run.tuning == Tuning()])
    section.notes.append(
        f"Load: a Rider process sending {LOAD_RATE:g} `check/home` commands/s (sequential, on an"
        " absolute schedule) and decoding every status / IO / axis / diag publication, while"
        " the machine runs the default session back to back."
    )
    section.notes.append(
        "↳ rows: the runner's own loop with an empty scan (bench/baselines/bare_loop.py), run"
        " at the same time and period as the daemon above it — what this host allowed at that"
        " moment. Empty runners in one group ran at the same time as each other."
    )
    section.notes.append(
        f"Under load the watchdog is set to {WATCHDOG_S * 1e3:g} ms (its default at 10 ms) so a"
        " host stall does not fault the machine and stop the motion; idle runs keep the"
        " default of 3 periods, and the cross-check table counts its trips."
    )
    section.notes.append(
        "Time slice: every thread of the daemon asks the kernel for a 0.1 ms slice under the"
        " normal policy (`loop.slice_s`, the default; Linux 6.12+'s EEVDF, no privilege, CPU"
        " shares unchanged) so a wake-up preempts a busy neighbour; `kernel time slice` rows"
        " run with `slice_s = 0`, the kernel's own slice, as before. The empty runners ask"
        " for the same slice as the daemon unless their row says otherwise."
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


if __name__ == "__main__":
    sys.exit(common.main_for("bench.loop_timing", __doc__ or "", run))
