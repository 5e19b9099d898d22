"""Every benchmark in one run (`make bench`): prints the tables and rewrites BENCHMARKS.md."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable

from bench import (
    busybox,
    confirm,
    cost,
    estop,
    events_cost,
    freeze,
    gateway,
    healthcheck,
    homing,
    loop_timing,
    pick,
    read_flood,
    retention,
    rider_cost,
    rider_loss,
    roundtrip,
    site,
    startup,
    status_latency,
    throughput,
)
from bench.common import (
    Options,
    Section,
    Table,
    build_parser,
    busy_percent,
    command_line,
    host_cpu,
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
    ("bench.events_cost", events_cost.run),
    ("bench.retention", retention.run),
    ("bench.rider_loss", rider_loss.run),
    ("bench.pick", pick.run),
    ("bench.throughput", throughput.run),
    ("bench.rider_cost", rider_cost.run),
    ("bench.read_flood", read_flood.run),
    ("bench.freeze", freeze.run),
    ("bench.healthcheck", healthcheck.run),
    ("bench.gateway", gateway.run),
    ("bench.homing", homing.run),
    ("bench.confirm", confirm.run),
    ("bench.startup", startup.run),
    ("bench.busybox", busybox.run),
    ("bench.site", site.run),
]


def run_all(opts: Options, command: str, flags: list[str]) -> Table:
    """Run each benchmark in turn, saving each section as soon as it is done."""
    summary = Table(
        "Run", ["benchmark", "seconds", "host CPU busy", "load avg before", "load avg after"]
    )
    t0 = time.monotonic()
    before = os.getloadavg()
    busy0 = host_cpu()
    for prog, run in BENCHMARKS:
        section = measure(run, opts, command_line(prog, flags), part_of=command)
        save(section, opts)
        summary.add(
            prog,
            f"{section.seconds:.0f}",
            f"{section.host_busy:.0f} %",
            "/".join(f"{x:.2f}" for x in section.load_before),
            "/".join(f"{x:.2f}" for x in section.load_after),
        )
    after = os.getloadavg()
    summary.add(
        "all",
        f"{time.monotonic() - t0:.0f}",
        f"{busy_percent(busy0, host_cpu()):.0f} %",
        "/".join(f"{x:.2f}" for x in before),
        "/".join(f"{x:.2f}" for x in after),
    )
    summary.note = (
        f"{time.strftime('%Y-%m-%d %H:%M %Z')}, `{command}`. Host CPU busy = share of both"
        " cores' time used by anyone (the benchmarks themselves included); load average ="
        " runnable tasks, 1/5/15-minute means — above 2 the two cores were oversubscribed"
    )
    return summary


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    opts = options_from(build_parser("bench.all", __doc__ or "").parse_args(argv))
    command = command_line("bench.all", argv)
    if os.environ.get("MAKELEVEL"):
        command = "make bench"
    with interrupts_as_exceptions():
        summary = run_all(opts, command, argv)
    print(summary.text())
    if opts.out is not None:
        write_section(opts.out, "run", "Run", summary.markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
