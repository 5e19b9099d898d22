"""The benchmarks run: each `--quick` smoke run finishes, writes its section, and leaves no
process behind, even when stopped midway. No timing is asserted: speed is what they report."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import IO

import pytest

from bench import all as bench_all
from bench.common import Dist, Options, Section, Table, Target, pct, write_section
from bench.cost import Idle, floor_targets

REPO = Path(__file__).resolve().parents[2]
MODULES = [
    "roundtrip",
    "loop_timing",
    "estop",
    "status_latency",
    "cost",
    "events_cost",
    "retention",
    "rider_loss",
    "pick",
    "throughput",
    "rider_cost",
    "read_flood",
    "freeze",
    "healthcheck",
    "gateway",
    "homing",
    "confirm",
    "startup",
    "busybox",
    "site",
]
MARKER = "BENCH_TEST_RUN"
RUN_TIMEOUT_S = 150.0
GONE_TIMEOUT_S = 10.0


def _marked_pids(marker: str) -> list[int]:
    """Processes whose environment carries this test's marker (the bench and its children)."""
    needle = f"{MARKER}={marker}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            env = (entry / "environ").read_bytes()
            stat = (entry / "stat").read_text()
        except OSError:
            continue  # exited meanwhile, or not ours to read
        if needle in env.split(b"\0") and stat.rsplit(")", 1)[1].split()[0] != "Z":
            found.append(int(entry.name))
    return found


def _left_behind(marker: str, timeout: float = GONE_TIMEOUT_S) -> list[int]:
    """The marked processes still running once `timeout` has passed, or none as soon as they
    are all gone: a daemon's history process ends on its own once its daemon has (its pipe
    closes), a moment after the bench that stopped the daemon has returned."""
    deadline = time.monotonic() + timeout
    while (left := _marked_pids(marker)) and time.monotonic() < deadline:
        time.sleep(0.05)
    return left


def _bench(
    module: str, marker: str, *args: str, out: IO[str] | None = None
) -> subprocess.Popen[str]:
    """`python -m bench.MODULE ARGS`, its output to `out` (a pipe when None)."""
    env = {**os.environ, MARKER: marker, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", f"bench.{module}", *args],
        cwd=REPO,
        env=env,
        stdout=out if out is not None else subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


PARALLEL = 3
"""Smoke runs at once. All thirteen at once (a dozen daemons, their Riders and baselines on two
cores) starved a daemon past its 20 s start on a loaded host: 'daemon not alive in time'."""


def _run_all(tmp_path: Path, marker: str) -> dict[str, int]:
    """Every module's `--quick` run, `PARALLEL` at a time, each bounded: exit codes by module
    (the output of each in tmp_path/MODULE.log)."""
    waiting, running, codes = list(MODULES), {}, {}
    try:
        while waiting or running:
            while waiting and len(running) < PARALLEL:
                m = waiting.pop(0)
                with (tmp_path / f"{m}.log").open("w") as log:
                    proc = _bench(m, marker, "--quick", "--out", str(tmp_path / f"{m}.md"), out=log)
                running[m] = (proc, time.monotonic() + RUN_TIMEOUT_S)
            for m, (proc, deadline) in list(running.items()):
                if proc.poll() is not None or time.monotonic() > deadline:
                    if proc.poll() is None:
                        proc.kill()
                        proc.wait(10)
                    codes[m] = proc.returncode
                    del running[m]
            time.sleep(0.1)
    finally:
        for proc, _ in running.values():
            proc.kill()
            proc.wait(10)
    return codes


@pytest.mark.integration
def test_every_benchmark_runs_quick_and_writes_its_section(tmp_path: Path) -> None:
    marker = uuid.uuid4().hex
    codes = _run_all(tmp_path, marker)
    for module in MODULES:
        output = (tmp_path / f"{module}.log").read_text()
        assert codes[module] == 0, f"bench.{module}:\n{output[-4000:]}"
        text = (tmp_path / f"{module}.md").read_text()
        assert f"<!-- bench:{module} -->" in text and f"<!-- /bench:{module} -->" in text
        assert "<!-- bench:machine -->" in text
        assert "**Targets**" in text, f"bench.{module} reported no target"
        assert "|---|" in text
    assert _left_behind(marker) == []


@pytest.mark.integration
def test_a_benchmark_stopped_midway_stops_its_children(tmp_path: Path) -> None:
    marker = uuid.uuid4().hex
    proc = _bench("roundtrip", marker, "--quick", "--no-write")
    try:
        deadline = time.monotonic() + 60.0
        # The bench, the daemon and at least two baseline servers are up.
        while len(_marked_pids(marker)) < 4:
            assert proc.poll() is None, proc.communicate()[0][-4000:]
            assert time.monotonic() < deadline, "children never started"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        proc.wait(60.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        if proc.stdout is not None:
            proc.stdout.close()
    assert _left_behind(marker) == []


def test_percentiles_are_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]
    assert pct(values, 0.50) == 50.0
    assert pct(values, 0.99) == 99.0
    assert pct(values, 1.0) == 100.0
    d = Dist.of(list(reversed(values)))
    assert (d.n, d.min, d.p50, d.p90, d.max) == (100, 1.0, 50.0, 90.0, 100.0)
    assert Dist.of([]).n == 0


def test_write_section_replaces_only_its_own_block(tmp_path: Path) -> None:
    path = tmp_path / "B.md"
    write_section(path, "a", "A", "first")
    with path.open("a") as fh:
        fh.write("\nHand-written analysis.\n")
    write_section(path, "b", "B", "other")
    write_section(path, "a", "A", "second")
    text = path.read_text()
    assert "second" in text and "first" not in text
    assert "Hand-written analysis." in text and "other" in text
    assert text.index("<!-- bench:a -->") < text.index("Hand-written") < text.index("bench:b")


def test_targets_say_by_how_much_they_were_missed() -> None:
    met = Target.at_most("x", 1.0, 2.0, str)
    missed = Target.at_most("x", 3.0, 2.0, str)
    assert met.met and met.verdict == "met"
    assert missed.met is False and "50 % over" in missed.verdict
    floor = Target.at_least("y", 1.5, 1.6, str)
    assert floor.goal == "≥ 1.6" and floor.met is False and "6 % short" in floor.verdict
    assert Target.at_least("y", 1.6, 1.6, str).verdict == "met"
    assert Target.at_least("y", float("nan"), 1.6, str).met is None


def test_cost_judges_the_idle_daemon_against_the_empty_runner_of_its_period() -> None:
    idles = [
        Idle("daemon, 10 ms", 0.010, 1.8, 0, 0, 20),
        Idle("empty runner, 10 ms", 0.010, 1.5, 0, 0, 2),
        Idle("daemon, 1 ms", 0.001, 7.0, 0, 0, 20),
        Idle("empty runner, 1 ms", 0.001, 5.0, 0, 0, 2),
        Idle("bare Zenoh session (echo queryable)", None, 0.8, 0, 0, 8),
    ]
    at_10, at_1 = floor_targets(idles)
    assert (at_10.measured, at_10.met) == ("1.20×", True)
    assert (at_1.measured, at_1.met) == ("1.40×", False)


def test_a_table_refuses_a_row_of_the_wrong_width() -> None:
    table = Table("t", ["a", "b"])
    table.add(1, 2)
    with pytest.raises(ValueError, match="2 columns"):
        table.add(1)
    assert table.markdown().splitlines()[-1] == "| 1 | 2 |"


def test_all_runs_each_benchmark_and_writes_every_section(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ran: list[bool] = []

    def fake(key: str) -> object:
        def run(opts: Options) -> Section:
            ran.append(opts.quick)
            section = Section(key, key.upper())
            section.tables.append(Table("T", ["k"], [[key]]))
            return section

        return run

    monkeypatch.setattr(bench_all, "BENCHMARKS", [("bench.x", fake("x")), ("bench.y", fake("y"))])
    out = tmp_path / "B.md"
    assert bench_all.main(["--quick", "--out", str(out)]) == 0
    text = out.read_text()
    assert ran == [True, True]
    for key in ("machine", "x", "y", "run"):
        assert f"<!-- bench:{key} -->" in text
