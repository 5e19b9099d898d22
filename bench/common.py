"""Shared by every benchmark: percentiles, tables, BENCHMARKS.md sections, child processes."""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import math
import os
import platform
import re
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import TextIO, TypeVar

import msgpack
import zenoh

from tests.procs import LineReader, stop_process

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "BENCHMARKS.md"
CLK_TCK = os.sysconf("SC_CLK_TCK")
NAN = float("nan")
T = TypeVar("T")


# ----------------------------------------------------------------------------- statistics
def pct(sorted_values: Sequence[float], q: float) -> float:
    """Nearest-rank percentile of already sorted values (NaN when there are none)."""
    if not sorted_values:
        return NAN
    k = max(1, math.ceil(q * len(sorted_values)))
    return sorted_values[k - 1]


@dataclass(frozen=True)
class Dist:
    """A sample of durations in seconds, summarised: count, mean, percentiles, extremes."""

    n: int
    mean: float
    min: float
    p50: float
    p90: float
    p99: float
    max: float

    @classmethod
    def of(cls, samples: Sequence[float]) -> Dist:
        s = sorted(samples)
        if not s:
            return cls(0, NAN, NAN, NAN, NAN, NAN, NAN)
        return cls(len(s), sum(s) / len(s), s[0], pct(s, 0.5), pct(s, 0.9), pct(s, 0.99), s[-1])


def growth_per_hour(ts: list[float], values: list[int]) -> float:
    """Least-squares slope of `values` over `ts` (seconds), per hour; NaN with fewer than two
    samples or all at one time."""
    try:
        fit = statistics.linear_regression(ts, [float(v) for v in values])
    except statistics.StatisticsError:
        return float("nan")
    return 3600.0 * fit.slope


def ms(seconds: float, digits: int = 3) -> str:
    """Seconds as milliseconds for a table cell."""
    return "—" if math.isnan(seconds) else f"{seconds * 1e3:.{digits}f}"


def us(seconds: float) -> str:
    """Seconds as whole microseconds for a table cell."""
    return "—" if math.isnan(seconds) else f"{seconds * 1e6:.0f}"


def share(value: float, whole: float) -> str:
    """`value` as a percentage of `whole` (e.g. jitter of the period)."""
    return "—" if math.isnan(value) or whole == 0 else f"{100 * value / whole:.1f} %"


# --------------------------------------------------------------------------------- tables
@dataclass
class Table:
    """Rows of text cells; rendered aligned for the terminal and as Markdown for the file."""

    title: str
    header: list[str]
    rows: list[list[str]] = field(default_factory=list)
    note: str = ""

    def add(self, *cells: object) -> None:
        if len(cells) != len(self.header):
            raise ValueError(f"{self.title}: {len(cells)} cells for {len(self.header)} columns")
        self.rows.append([str(c) for c in cells])

    def text(self) -> str:
        widths = [len(h) for h in self.header]
        for row in self.rows:
            widths = [max(w, len(c)) for w, c in zip(widths, row, strict=True)]
        lines = [
            self.title,
            "  ".join(h.ljust(w) for h, w in zip(self.header, widths, strict=True)),
        ]
        lines.append("  ".join("-" * w for w in widths))
        lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in self.rows]
        if self.note:
            lines.append(f"  ({self.note})")
        return "\n".join(lines)

    def markdown(self) -> str:
        lines = [f"**{self.title}**", "", "| " + " | ".join(self.header) + " |"]
        lines.append("|" + "|".join(["---"] + ["--:"] * (len(self.header) - 1)) + "|")
        lines += ["| " + " | ".join(r) + " |" for r in self.rows]
        if self.note:
            lines += ["", f"_{self.note}_"]
        return "\n".join(lines)


@dataclass(frozen=True)
class Target:
    """One target of the issue: the goal, what was measured, and whether it was met."""

    what: str
    goal: str
    measured: str
    met: bool | None
    detail: str = ""

    @classmethod
    def at_most(cls, what: str, value: float, limit: float, fmt: Callable[[float], str]) -> Target:
        """Met when `value <= limit`; otherwise says by how much it was missed."""
        if math.isnan(value):
            return cls(what, f"≤ {fmt(limit)}", "—", None, "not measured")
        met = value <= limit
        detail = "" if met else f"{100 * (value / limit - 1):.0f} % over"
        return cls(what, f"≤ {fmt(limit)}", fmt(value), met, detail)

    @classmethod
    def at_least(cls, what: str, value: float, limit: float, fmt: Callable[[float], str]) -> Target:
        """Met when `value >= limit`; otherwise says by how much it fell short."""
        if math.isnan(value):
            return cls(what, f"≥ {fmt(limit)}", "—", None, "not measured")
        met = value >= limit
        detail = "" if met else f"{100 * (1 - value / limit):.0f} % short"
        return cls(what, f"≥ {fmt(limit)}", fmt(value), met, detail)

    @property
    def verdict(self) -> str:
        if self.met is None:
            return "n/a" + (f": {self.detail}" if self.detail else "")
        if self.met:
            return "met"
        return f"**missed**, {self.detail}" if self.detail else "**missed**"


def targets_table(targets: Sequence[Target]) -> Table:
    table = Table("Targets", ["target", "goal", "measured", "verdict"])
    for t in targets:
        table.add(t.what, t.goal, t.measured, t.verdict)
    return table


# ------------------------------------------------------------------------------- sections
@dataclass
class Section:
    """One benchmark's results: tables, targets and notes, with when and how they were taken."""

    key: str
    title: str
    tables: list[Table] = field(default_factory=list)
    targets: list[Target] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    command: str = ""
    date: str = ""
    load_before: tuple[float, float, float] = (NAN, NAN, NAN)
    load_after: tuple[float, float, float] = (NAN, NAN, NAN)
    seconds: float = NAN
    host_busy: float = NAN
    """Percent of all the host's CPU time that was busy (anyone's) during the benchmark."""
    part_of: str = ""

    def provenance(self) -> str:
        part = f" (part of `{self.part_of}`)" if self.part_of else ""
        return (
            f"Measured {self.date} with `{self.command}`{part} in {self.seconds:.0f} s; host CPU"
            f" {self.host_busy:.0f} % busy; load average (1/5/15 min) before"
            f" {_load(self.load_before)}, after {_load(self.load_after)}."
        )

    def all_tables(self) -> list[Table]:
        return [*self.tables, targets_table(self.targets)] if self.targets else self.tables

    def text(self) -> str:
        parts = [f"== {self.title} ==", self.provenance()]
        parts += [t.text() for t in self.all_tables()]
        parts += [f"* {n}" for n in self.notes]
        return "\n\n".join(parts)

    def markdown(self) -> str:
        parts = [self.provenance()]
        parts += [t.markdown() for t in self.all_tables()]
        if self.notes:
            parts.append("\n".join(f"- {n}" for n in self.notes))
        return "\n\n".join(parts)


def _load(load: tuple[float, float, float]) -> str:
    return "/".join(f"{x:.2f}" for x in load)


HEADER = """# Benchmarks

Generated by `make bench` (or one script alone, e.g. `python -m bench.roundtrip`). Text between
`<!-- bench:... -->` markers is rewritten by the scripts; everything else is written by hand.
"""


def write_section(path: Path, key: str, title: str, body: str) -> None:
    """Replace the marked block `key` in `path` (created if missing), keeping all other text."""
    text = path.read_text() if path.exists() else HEADER
    begin, end = f"<!-- bench:{key} -->", f"<!-- /bench:{key} -->"
    block = f"{begin}\n{body}\n{end}"
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.DOTALL)
    if pattern.search(text):
        text = pattern.sub(lambda _: block, text, count=1)
    else:
        text = text.rstrip("\n") + f"\n\n## {title}\n\n{block}\n"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def machine_info() -> Table:
    """CPU, cores, kernel and the versions that matter to the numbers."""
    model = "unknown"
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as fh:
        for line in fh:
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    table = Table("Machine", ["what", "value"])
    table.add("CPU", model)
    table.add("cores", str(os.cpu_count()))
    table.add("kernel", f"{platform.system()} {platform.release()}")
    table.add("Python", f"{platform.python_implementation()} {platform.python_version()}")
    table.add("eclipse-zenoh", _version("eclipse-zenoh"))
    table.add("grpcio", _version("grpcio"))
    return table


def write_machine(path: Path) -> None:
    write_section(path, "machine", "Machine", machine_info().markdown())


# -------------------------------------------------------------------------------- options
@dataclass(frozen=True)
class Options:
    """How long to measure (`--quick` smoke run, default, `--long`) and where to write."""

    quick: bool = False
    long: bool = False
    out: Path | None = RESULTS

    def pick(self, quick: T, normal: T, long: T | None = None) -> T:
        if self.quick:
            return quick
        if self.long and long is not None:
            return long
        return normal


def build_parser(prog: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=description)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="a few seconds: a smoke run")
    size.add_argument("--long", action="store_true", help="long runs (10 min loop timing)")
    parser.add_argument(
        "--out",
        type=Path,
        help="Markdown file to update (default BENCHMARKS.md; --quick writes only with --out)",
    )
    parser.add_argument("--no-write", action="store_true", help="print tables only")
    return parser


def soak_parser(prog: str, description: str, minutes: float) -> argparse.ArgumentParser:
    """The soaks' options: a duration instead of `--quick`/`--long`, and where to write."""
    parser = argparse.ArgumentParser(prog=f"python -m {prog}", description=description)
    parser.add_argument(
        "--minutes", type=float, default=minutes, help=f"soak duration (default {minutes:g})"
    )
    parser.add_argument("--out", type=Path, default=RESULTS, help="Markdown file to update")
    parser.add_argument("--no-write", action="store_true", help="print the tables only")
    return parser


def options_from(args: argparse.Namespace) -> Options:
    out: Path | None = args.out
    if out is None and not args.quick:
        out = RESULTS
    if args.no_write:
        out = None
    return Options(quick=args.quick, long=args.long, out=out)


def command_line(prog: str, argv: Sequence[str]) -> str:
    return " ".join([f"python -m {prog}", *argv])


def measure(
    run: Callable[[Options], Section],
    opts: Options,
    command: str,
    out: TextIO = sys.stdout,
    part_of: str = "",
) -> Section:
    """Run one benchmark and stamp its section with date, command, load and duration."""
    before = os.getloadavg()
    busy0 = host_cpu()
    t0 = time.monotonic()
    section = run(opts)
    section.seconds = time.monotonic() - t0
    section.host_busy = busy_percent(busy0, host_cpu())
    section.load_before, section.load_after = before, os.getloadavg()
    section.date = time.strftime("%Y-%m-%d %H:%M %Z")
    section.command = command
    section.part_of = part_of
    print(section.text(), file=out, flush=True)
    print(file=out)
    return section


def save(section: Section, opts: Options) -> None:
    if opts.out is not None:
        write_machine(opts.out)
        write_section(opts.out, section.key, section.title, section.markdown())
        print(f"wrote section {section.key!r} of {opts.out}")


def main_for(
    prog: str, description: str, run: Callable[[Options], Section], argv: list[str] | None = None
) -> int:
    """The `python -m bench.<name>` entry point shared by every benchmark."""
    argv = sys.argv[1:] if argv is None else argv
    opts = options_from(build_parser(prog, description).parse_args(argv))
    with interrupts_as_exceptions():
        save(measure(run, opts, command_line(prog, argv)), opts)
    return 0


def main_quiet(
    prog: str, description: str, run: Callable[[Options], Section], argv: list[str] | None = None
) -> int:
    """`main_for`, where an interrupt ends the benchmark with exit 1 and no traceback."""
    with contextlib.suppress(KeyboardInterrupt):
        return main_for(prog, description, run, argv)
    return 1


def main_or_child(
    prog: str,
    description: str,
    run: Callable[[Options], Section],
    argv: list[str] | None,
    children: Mapping[str, Callable[[list[str]], int]],
) -> int:
    """`main_for`, unless the first argument names one of the benchmark's child processes
    (`python -m bench.<name> <child> …`, started by the benchmark itself): then that child."""
    argv = sys.argv[1:] if argv is None else argv
    child = children.get(argv[0]) if argv else None
    if child is not None:
        return child(argv[1:])
    return main_for(prog, description, run, argv)


def child_parser(prog: str, *, connect: str = "store") -> argparse.ArgumentParser:
    """The options every benchmark child process takes: where to connect, which Zenoh config
    (`connect="append"`: several endpoints)."""
    parser = argparse.ArgumentParser(prog=prog)
    parser.add_argument("--connect", action=connect, required=True)
    parser.add_argument("--zenoh-config", type=Path, required=True)
    return parser


def measure_and_save(run: Callable[[], Section], out: Path | None, command: str) -> None:
    """`measure` and `save` for a benchmark with its own options (the soaks: no `--quick`)."""
    opts = Options(out=out)
    with interrupts_as_exceptions():
        save(measure(lambda _: run(), opts, command), opts)


@contextlib.contextmanager
def interrupts_as_exceptions() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt like Ctrl-C does, so `finally` blocks stop children."""

    def on_term(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# -------------------------------------------------------------------------- child processes
STOP_TIMEOUT_S = 10.0


class Child:
    """A child process whose stdout the benchmark reads line by line (stderr goes to a log)."""

    def __init__(self, args: list[str], log: Path, *, stdin: bool = False) -> None:
        """`stdin`: a pipe the benchmark writes to (`send`) instead of the inherited stdin."""
        self.args = args
        self.log_path = log
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        with log.open("w") as err:
            self.proc = subprocess.Popen(
                args,
                stdin=subprocess.PIPE if stdin else None,
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
                cwd=REPO,
                env=env,
            )
        self._lines: LineReader | None = None

    def send(self, line: str) -> None:
        """One line to the child's stdin (started with `stdin=True`)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def line(self, timeout: float) -> str:
        """The next stdout line; raises TimeoutError or RuntimeError if the child died."""
        assert self.proc.stdout is not None
        if self._lines is None:
            self._lines = LineReader(self.proc.stdout)
        try:
            text = self._lines.line(timeout)
        except TimeoutError:
            raise TimeoutError(f"no output from {self.args[2:4]} in {timeout:g} s") from None
        if text is None:
            self.proc.wait(STOP_TIMEOUT_S)
            raise RuntimeError(
                f"{self.args[2:4]} exited with {self.proc.returncode}: {self.log()[-2000:]}"
            )
        return text

    def expect(self, prefix: str, timeout: float = 20.0) -> str:
        """Skip lines until one starts with `prefix`; returns the rest of it."""
        deadline = time.monotonic() + timeout
        while True:
            text = self.line(max(0.0, deadline - time.monotonic()))
            if text.startswith(prefix):
                return text[len(prefix) :].strip()

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""

    def stop(self, sig: int = signal.SIGTERM) -> int:
        """Signal, wait (bounded), then kill; returns the exit code."""
        stop_process(self.proc, sig)
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None:
                with contextlib.suppress(OSError):
                    pipe.close()
        return self.proc.returncode


def run_lines() -> Iterator[list[str]]:
    """A helper process's side of `Child.send`: the arguments of each `run ...` line on its
    stdin, until any other line or the end of input."""
    for line in sys.stdin:
        parts = line.split()
        if not parts or parts[0] != "run":
            return
        yield parts[1:]


def tenths(n: int, rows: int = 10) -> list[int]:
    """Indices of `n` samples for a curve over a run: one per tenth (`rows`), and the last."""
    picked = list(range(0, n, max(1, n // rows)))
    if picked and picked[-1] != n - 1:
        picked.append(n - 1)
    return picked


def command_request(transaction_id: str) -> bytes:
    """The msgpack body of a benchmark's raw command get: its id and the time it is sent."""
    body = {"transaction_id": transaction_id, "timecode": time.time(), "rider": None}
    return bytes(msgpack.packb(body))


def only_reply(replies: list[zenoh.Reply], key: str) -> bytes:
    """The payload of the one ok reply a benchmark's get expects; RuntimeError otherwise."""
    if len(replies) != 1 or replies[0].ok is None:
        raise RuntimeError(f"{key}: expected one reply, got {len(replies)}")
    return replies[0].ok.payload.to_bytes()


def python_module(module: str, *args: object) -> list[str]:
    return [sys.executable, "-m", module, *(str(a) for a in args)]


def start_module(
    stack: contextlib.ExitStack, log: Path, module: str, *args: object, stdin: bool = False
) -> Child:
    """`python -m module args` as a `Child` that logs to `log`, stopped when `stack` closes."""
    child = Child(python_module(module, *args), log, stdin=stdin)
    stack.callback(child.stop)
    return child


@contextlib.contextmanager
def burners(n: int, tmp: Path, lifetime_s: float) -> Iterator[list[Child]]:
    """`n` CPU-bound processes (bench.baselines.burner, each gone after `lifetime_s` at the
    latest) for the block, all ready when it begins."""
    with contextlib.ExitStack() as stack:
        started = [
            start_module(
                stack, tmp / f"burner-{i}.log", "bench.baselines.burner", "--lifetime", lifetime_s
            )
            for i in range(n)
        ]
        for burner in started:
            burner.expect("ready")
        yield started


# ---------------------------------------------------------------------------------- /proc
def host_cpu() -> tuple[int, int]:
    """(busy, total) CPU ticks of the whole host so far, from /proc/stat."""
    with open("/proc/stat") as fh:
        ticks = [int(x) for x in fh.readline().split()[1:]]
    idle = ticks[3] + ticks[4]  # idle + iowait
    return sum(ticks) - idle, sum(ticks)


def busy_percent(before: tuple[int, int], after: tuple[int, int]) -> float:
    total = after[1] - before[1]
    return 100.0 * (after[0] - before[0]) / total if total > 0 else NAN


def children(pid: int) -> list[int]:
    """The processes `pid` started that still run (a daemon's event history process,
    service/adapters/history.py)."""
    out: list[int] = []
    with contextlib.suppress(OSError):
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError), open(f"/proc/{pid}/task/{tid}/children") as fh:
                out.extend(int(c) for c in fh.read().split())
    return out


def cpu_seconds(pid: int, *, family: bool = False) -> float:
    """User + system CPU seconds of a process (all its threads); `family`: with its running
    child processes' (a daemon's CPU includes its history process)."""
    total = 0.0
    for each in [pid, *children(pid)] if family else [pid]:
        try:
            with open(f"/proc/{each}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            if each == pid:
                raise
            continue  # a child that ended meanwhile
        total += (int(fields[11]) + int(fields[12])) / CLK_TCK
    return total


ZENOH_THREAD = re.compile(r"(app|rx|tx|net|acc)-\d+")
"""The names Zenoh's runtimes give their threads (one `app-0` under `bus.zenoh_threads = 1`)."""


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds of process `pid` by thread: Zenoh's runtime threads as `zenoh`, the main
    thread (the daemon's scan thread) as `main`, every other under the name it gave the OS
    (service/threads.py), summed per name. From each thread's `schedstat` (ns); a thread
    that ends between two calls takes its time with it."""
    out: dict[str, float] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as fh:
                name = fh.read().strip()
            with open(f"/proc/{pid}/task/{tid}/schedstat") as fh:
                ns = int(fh.read().split()[0])
        except (OSError, ValueError, IndexError):
            continue  # ended meanwhile
        key = "main" if tid == str(pid) else "zenoh" if ZENOH_THREAD.fullmatch(name) else name
        out[key] = out.get(key, 0.0) + ns / 1e9
    for child in children(pid):  # the history process, all its threads as one
        spent = sum(thread_cpu(child).values())
        out[HISTORY] = out.get(HISTORY, 0.0) + spent
    return out


HISTORY = "history"
"""`thread_cpu`'s key for the daemon's child processes (the event history's)."""


def rss_bytes(pid: int, *, family: bool = False) -> int:
    """Resident set size of a process; `family`: with its running child processes'."""
    total = 0
    for each in [pid, *children(pid)] if family else [pid]:
        try:
            with open(f"/proc/{each}/status") as fh:
                total += next(
                    (int(line.split()[1]) * 1024 for line in fh if line.startswith("VmRSS:")), 0
                )
        except OSError:
            if each == pid:
                raise
    return total


@dataclass
class CpuMeter:
    """CPU % of one core used by a process between `start()` and `stop()`."""

    pid: int
    family: bool = False
    """With the process's children (a daemon's history process: `cpu_seconds`)."""
    t0: float = 0.0
    c0: float = 0.0

    def start(self) -> None:
        self.t0, self.c0 = time.monotonic(), cpu_seconds(self.pid, family=self.family)

    def percent(self) -> float:
        dt = time.monotonic() - self.t0
        spent = cpu_seconds(self.pid, family=self.family) - self.c0
        return 100.0 * spent / dt if dt > 0 else NAN


def mib(n: int) -> str:
    return f"{n / 2**20:.1f}"
