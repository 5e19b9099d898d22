"""Every benchmark in one run (`make bench`): prints the tables and rewrites BENCHMARKS.md."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable

from bench import cost, estop, loop_timing, roundtrip, status_latency
from bench.common import (
    Options,
    Section,
    Table,
    build_parser,
    command_line,
    interrupts_as_exceptions,
    measure,
    options_from,
    save,
    write_section,
)

BENCHMARKS: list[tuple[str, Callable[[Options], Section]]] = [
    ("bench.roundtrip", roundtrip.run),
    ("bench.loop_timing", loop_timing.run),
    ("bench.estop", estop.run),
    ("bench.status_latency", status_latency.run),
    ("bench.cost", cost.run),
]


def run_all(opts: Options, command: str) -> Table:
    """Run each benchmark in turn, saving each section as soon as it is done."""
    summary = Table("Run", ["benchmark", "seconds", "load avg before", "load avg after"])
    t0 = time.monotonic()
    before = os.getloadavg()
    for prog, run in BENCHMARKS:
        section = measure(run, opts, f"{command} ({prog})")
        save(section, opts)
        summary.add(
            prog,
            f"{section.seconds:.0f}",
            "/".join(f"{x:.2f}" for x in section.load_before),
            "/".join(f"{x:.2f}" for x in section.load_after),
        )
    after = os.getloadavg()
    summary.add(
        "all",
        f"{time.monotonic() - t0:.0f}",
        "/".join(f"{x:.2f}" for x in before),
        "/".join(f"{x:.2f}" for x in after),
    )
    summary.note = (
        f"{time.strftime('%Y-%m-%d %H:%M %Z')}, `{command}`; load average = 1/5/15-minute run"
        " queue of this shared 2-core machine (other work was running: numbers are noisy)"
    )
    return summary


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    opts = options_from(build_parser("bench.all", __doc__ or "").parse_args(argv))
    command = command_line("bench.all", argv)
    with interrupts_as_exceptions():
        summary = run_all(opts, command)
    print(summary.text())
    if opts.out is not None:
        write_section(opts.out, "run", "Run", summary.markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
