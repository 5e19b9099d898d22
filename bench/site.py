"""A site of many machines through one router: what grows with the number of machines (issue 59).

`python -m bench.site --machines 50` starts, on this host, one router (tests/site/router.py:
a Python Zenoh session in `router` mode with docs/site.md's router config, the stand-in for
zenohd the site tests use), simulated daemons joined to it, and `rider gateway` connected to
the router. One host has to carry them all, so the daemons run a relaxed scan period
(`PERIOD_S`, 50 ms instead of 10 ms) and a watchdog that tolerates a loaded host; everything
else is the shipped default (a status heartbeat every second, the event history in its own
process). Daemons join as `--mode client` (the default here: a client links only to the
router) or `peer` (docs/site.md's recommendation for daemons: peers link to each other too).

Two phases in one run, the baseline first: `--baseline` machines (10, the largest site
measured before), then the fleet grown to `--machines`. In each phase, once every machine is
alive and the gateway shows it:

- the fleet's join: from the first daemon's exec until a Rider on the router has every token,
  and until the gateway's Prometheus endpoint lists every machine;
- `rider machines` (a client Rider through the router, a fresh process each run): its wall time
  until it prints the list, which must hold every machine;
- a site-wide `rider --machine '*' events` (every machine's `daemon_start`): wall time and the
  machines that answered, which must be all;
- CPU (share of one core) of the router while the Rider commands above ran, then of the router,
  the gateway and the daemons over a quiet window; RSS and open sockets of each.

Every wait is bounded and every process is stopped at the end, also when interrupted.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from bench import common
from bench.common import mib, ms
from ride_machine.rider.client import Rider
from tests.procs import REPO, Daemon, free_port, start_daemon, stop_process
from tests.site.stand import PEER_CONFIG, Router, wait_tokens, write_doc_config

PERIOD_S = 0.050
MACHINES = 50
BASELINE = 10
JOIN_TIMEOUT_S = 60.0
"""Bound on a phase's join, plus `JOIN_PER_MACHINE_S` per machine started."""
JOIN_PER_MACHINE_S = 2.0
CLI_TIMEOUT_S = 60.0
LIST_TARGET_S = 2.0
"""`rider machines` with the whole site listed: within the 2 s a Rider's discovery may take."""
CONFIG = """\
# bench.site: a relaxed scan so one host carries the whole site; a watchdog that tolerates it.
[loop]
period_s = {period_s!r}
watchdog_periods = 100
"""
_ALIVE = re.compile(r'^ride_machine_alive\{machine="([^"]+)"\} 1\.0$', re.M)


@dataclass
class Phase:
    """What one phase measured, with `machines` alive."""

    machines: int
    join_tokens_s: float = float("nan")
    join_gateway_s: float = float("nan")
    token_after_bus: common.Dist = field(default_factory=lambda: common.Dist.of([]))
    """From a new daemon's bus up (its log) to its token at a Rider on the router."""
    listing: common.Dist = field(default_factory=lambda: common.Dist.of([]))
    listed: int = 0
    events: common.Dist = field(default_factory=lambda: common.Dist.of([]))
    answered: int = 0
    cpu: dict[str, float] = field(default_factory=dict)
    """Share of one core over the quiet window, by process group."""
    router_busy: float = float("nan")
    """The router's share of one core while the Rider commands ran."""
    rss: dict[str, int] = field(default_factory=dict)
    sockets: dict[str, float] = field(default_factory=dict)


class Stand:
    """The router, the daemons and the gateway; `close` stops them all (bounded)."""

    def __init__(self, tmp: Path, mode: str) -> None:
        self.tmp = tmp
        self.config = tmp / "machine-site.toml"
        self.config.write_text(CONFIG.format(period_s=PERIOD_S))
        self.client_config = write_doc_config(tmp, "client")
        self.daemon_zconf = PEER_CONFIG if mode == "peer" else self.client_config
        self.router = Router(write_doc_config(tmp, "router"), tmp)
        self.daemons: dict[str, Daemon] = {}
        self.gateway: subprocess.Popen[str] | None = None
        self.metrics_port = free_port()

    def start_router(self) -> None:
        self.router.start()

    @property
    def router_pid(self) -> int:
        assert self.router.proc is not None
        return self.router.proc.pid

    def add(self, count: int) -> list[str]:
        """Start `count` more daemons at once (not waiting for them); their ids."""
        ids = [f"s{len(self.daemons) + i:03d}" for i in range(count)]
        for mid in ids:
            extra = ["--config", str(self.config), "--zenoh-config", str(self.daemon_zconf)]
            extra += ["--connect", self.router.endpoint]
            self.daemons[mid] = start_daemon(self.tmp, mid, extra=extra, wait=False)
        return ids

    def rider(self) -> Rider:
        """A client Rider connected only to the router."""
        return Rider(
            None, connect=[self.router.endpoint], zenoh_config_path=self.client_config, timeout=5
        )

    def rider_cmd(self, *args: str) -> list[str]:
        return [
            *[sys.executable, "-m", "ride_machine.rider.cli", "--connect", self.router.endpoint],
            *["--zenoh-config", str(self.client_config), *args],
        ]

    def start_gateway(self) -> None:
        cmd = self.rider_cmd(
            "gateway",
            *["--opcua", f"127.0.0.1:{free_port()}"],
            *["--metrics", f"127.0.0.1:{self.metrics_port}"],
            *["--log-level", "warning", "--cache-dir", str(self.tmp / "gateway-cache")],
        )
        with (self.tmp / "gateway.log").open("w") as log:
            self.gateway = subprocess.Popen(
                cmd, stdout=log, stderr=subprocess.STDOUT, text=True, cwd=REPO
            )

    def gateway_alive(self) -> set[str]:
        """The machines the gateway's Prometheus endpoint says are alive."""
        try:
            url = f"http://127.0.0.1:{self.metrics_port}/metrics"
            with urllib.request.urlopen(url, timeout=5) as reply:
                return set(_ALIVE.findall(reply.read().decode()))
        except OSError:
            return set()

    @property
    def gateway_pid(self) -> int:
        assert self.gateway is not None
        return self.gateway.pid

    def close(self) -> None:
        """Signal every daemon first, then wait for each (bounded), then the gateway, the
        router."""
        for daemon in self.daemons.values():
            with contextlib.suppress(ProcessLookupError):
                daemon.proc.send_signal(signal.SIGTERM)
        for daemon in self.daemons.values():
            daemon.stop()
        if self.gateway is not None:
            stop_process(self.gateway)
        self.router.kill(signal.SIGTERM)


@contextlib.contextmanager
def stand(mode: str) -> Iterator[Stand]:
    with tempfile.TemporaryDirectory(prefix="bench-site-") as tmp_name:
        site = Stand(Path(tmp_name), mode)
        try:
            site.start_router()
            yield site
        finally:
            site.close()


# ------------------------------------------------------------------------------ measuring
def join(site: Stand, count: int, phase: Phase) -> None:
    """Start `count` more daemons with a Rider on the router already following the tokens;
    wait until it has every token, then until the gateway lists every machine (seconds since
    the first new daemon's exec), and how long each new token took from its daemon's bus."""
    timeout = JOIN_TIMEOUT_S + JOIN_PER_MACHINE_S * count
    with site.rider() as rider:
        changes = rider.follow_machines(timeout=0.2)
        wall_offset = time.time() - time.monotonic()
        began = time.monotonic()
        ids = site.add(count)
        if site.gateway is None:
            site.start_gateway()
        wanted = dict.fromkeys(site.daemons, True)
        reached = wait_tokens(changes, wanted, timeout, site.daemons)
    phase.join_tokens_s = max(reached[mid] for mid in ids) - began
    bus_up = {mid: _bus_started(site.daemons[mid].log_path) for mid in ids}
    phase.token_after_bus = common.Dist.of(
        [reached[mid] + wall_offset - up for mid, up in bus_up.items() if up is not None]
    )
    deadline = time.monotonic() + timeout
    while len(site.gateway_alive() & set(site.daemons)) < len(site.daemons):
        if site.gateway is not None and site.gateway.poll() is not None:
            raise RuntimeError(f"gateway exited: {(site.tmp / 'gateway.log').read_text()[-2000:]}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"the gateway did not list {len(site.daemons)} machines")
        time.sleep(0.1)
    phase.join_gateway_s = time.monotonic() - began


def _bus_started(log: Path) -> float | None:
    """When the daemon's bus came up (wall clock, its log's `event=bus_started` line)."""
    for line in log.read_text().splitlines():
        stamp = re.match(r"ts=(\S+)Z .*\bevent=bus_started\b", line)
        if stamp:
            return datetime.fromisoformat(stamp.group(1) + "+00:00").timestamp()
    return None


def sockets(pid: int) -> int:
    """The sockets process `pid` holds open (its Zenoh links, and whatever it listens on)."""
    count = 0
    with contextlib.suppress(OSError):
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with contextlib.suppress(OSError):
                count += os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:")
    return count


def _run_cli(cmd: list[str]) -> tuple[float, str]:
    began = time.perf_counter()
    done = subprocess.run(
        cmd, capture_output=True, text=True, check=False, timeout=CLI_TIMEOUT_S, cwd=REPO
    )
    took = time.perf_counter() - began
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[-4:])} exited {done.returncode}: {done.stderr[-2000:]}")
    return took, done.stdout


def listing_once(site: Stand) -> tuple[float, int]:
    """One `rider machines --json`: its wall time and how many machines it listed."""
    took, out = _run_cli(site.rider_cmd("--json", "machines"))
    return took, len({m["id"] for m in json.loads(out)})


def events_once(site: Stand) -> tuple[float, int]:
    """One site-wide `rider --machine '*' events`: wall time and the machines that answered."""
    cmd = site.rider_cmd("--machine", "*", "events", "--kind", "daemon_start", "--since", "1d")
    took, out = _run_cli([*cmd, "--json"])
    return took, len({json.loads(line)["machine_id"] for line in out.splitlines() if line})


def rounds(site: Stand, runs: int, phase: Phase) -> None:
    """`runs` of each Rider command, interleaved; the router's CPU meanwhile."""
    listings: list[float] = []
    queries: list[float] = []
    c0, t0 = common.cpu_seconds(site.router_pid), time.monotonic()
    listed, answered = len(site.daemons), len(site.daemons)
    for _ in range(runs):
        took, n = listing_once(site)
        listings.append(took)
        listed = min(listed, n)
        took, n = events_once(site)
        queries.append(took)
        answered = min(answered, n)
    phase.router_busy = 100 * (common.cpu_seconds(site.router_pid) - c0) / (time.monotonic() - t0)
    phase.listing, phase.listed = common.Dist.of(listings), listed
    phase.events, phase.answered = common.Dist.of(queries), answered


def quiet_window(site: Stand, seconds: float, phase: Phase) -> None:
    """CPU shares and RSS over `seconds` with nothing asked of the site."""
    daemon_pids = [d.proc.pid for d in site.daemons.values()]
    groups: dict[str, Callable[[], float]] = {
        "router": lambda: common.cpu_seconds(site.router_pid),
        "gateway": lambda: common.cpu_seconds(site.gateway_pid),
        "daemons (with their history processes)": lambda: sum(
            common.cpu_seconds(pid, family=True) for pid in daemon_pids
        ),
    }
    before = {name: read() for name, read in groups.items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    dt = time.monotonic() - t0
    phase.cpu = {name: 100 * (read() - before[name]) / dt for name, read in groups.items()}
    phase.rss = {
        "router": common.rss_bytes(site.router_pid),
        "gateway": common.rss_bytes(site.gateway_pid),
        "one daemon + its history process (mean)": sum(
            common.rss_bytes(pid, family=True) for pid in daemon_pids
        )
        // len(daemon_pids),
    }
    phase.sockets = {
        "router": sockets(site.router_pid),
        "gateway": sockets(site.gateway_pid),
        "one daemon (mean)": sum(sockets(pid) for pid in daemon_pids) / len(daemon_pids),
    }


def measure_site(opts: common.Options, machines: int, baseline: int, mode: str) -> list[Phase]:
    runs = opts.pick(2, 10, 20)
    window = opts.pick(2.0, 10.0, 30.0)
    phases: list[Phase] = []
    with stand(mode) as site:
        for target in (baseline, machines):
            phase = Phase(target)
            join(site, target - len(site.daemons), phase)
            rounds(site, runs, phase)
            quiet_window(site, window, phase)
            phases.append(phase)
    return phases


# -------------------------------------------------------------------------------- reporting
def _s(seconds: float) -> str:
    return "—" if math.isnan(seconds) else f"{seconds:.2f}"


def report(phases: list[Phase], mode: str) -> common.Section:
    load = os.getloadavg()
    cols = [f"{p.machines} machines" for p in phases]
    table = common.Table(
        f"The site, {' then '.join(cols)} (daemons as {mode}s, {PERIOD_S * 1e3:.0f} ms scan)",
        ["what", *cols],
        note="one router, one gateway on the router; the Rider commands are fresh client"
        f" processes through the router; host load average (1/5/15 min) at the end"
        f" {load[0]:.2f}/{load[1]:.2f}/{load[2]:.2f}",
    )
    table.add(
        "join: first exec → every token at a Rider, s", *[_s(p.join_tokens_s) for p in phases]
    )
    table.add("join: first exec → gateway lists all, s", *[_s(p.join_gateway_s) for p in phases])
    table.add(
        "a new token: bus up → seen at a Rider, p50 ms",
        *[ms(p.token_after_bus.p50, 0) for p in phases],
    )
    table.add(
        "a new token: bus up → seen at a Rider, max ms",
        *[ms(p.token_after_bus.max, 0) for p in phases],
    )
    table.add("`rider machines`, p50 ms", *[ms(p.listing.p50, 0) for p in phases])
    table.add("`rider machines`, max ms", *[ms(p.listing.max, 0) for p in phases])
    table.add("`rider machines`, fewest listed", *[str(p.listed) for p in phases])
    table.add("site-wide `rider events`, p50 ms", *[ms(p.events.p50, 0) for p in phases])
    table.add("site-wide `rider events`, max ms", *[ms(p.events.max, 0) for p in phases])
    table.add("site-wide `rider events`, fewest answered", *[str(p.answered) for p in phases])
    for name in phases[0].cpu:
        table.add(f"CPU, quiet: {name}, %", *[f"{p.cpu[name]:.1f}" for p in phases])
    table.add("CPU: router during the Rider commands, %", *[f"{p.router_busy:.1f}" for p in phases])
    for name in phases[0].rss:
        table.add(f"RSS: {name}, MiB", *[mib(p.rss[name]) for p in phases])
    for name in phases[0].sockets:
        table.add(f"sockets open: {name}", *[f"{p.sockets[name]:.0f}" for p in phases])
    last = phases[-1]
    return common.Section(
        "site" if mode == "client" else f"site-{mode}",
        f"A site of many machines through one router ({mode} daemons)",
        tables=[table],
        targets=[
            common.Target.at_most(
                f"`rider machines` with {last.machines}, p50", last.listing.p50, LIST_TARGET_S, _s
            ),
            common.Target(
                f"`rider machines` lists all {last.machines}",
                f"{last.machines}",
                str(last.listed),
                last.listed == last.machines,
            ),
            common.Target(
                f"site-wide `rider events` answered by all {last.machines}",
                f"{last.machines}",
                str(last.answered),
                last.answered == last.machines,
            ),
        ],
        notes=[
            "The router is tests/site/router.py (eclipse-zenoh's router mode in a Python"
            " process), not zenohd: the same routing code, with Python's start-up and memory"
            " added. docs/site.md turns these figures into an estimate for 500 machines.",
        ],
    )


def run(opts: common.Options) -> common.Section:
    """The `make bench` entry: the default site (a small one with `--quick`)."""
    machines, baseline = opts.pick((4, 2), (MACHINES, BASELINE))
    return report(measure_site(opts, machines, baseline, "client"), "client")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = common.build_parser("bench.site", __doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=MACHINES, help="the grown site's size")
    parser.add_argument("--baseline", type=int, default=BASELINE, help="the first phase's size")
    parser.add_argument("--mode", choices=["client", "peer"], default="client")
    args = parser.parse_args(argv)
    if not 1 <= args.baseline < args.machines:
        parser.error("--baseline must be at least 1 and smaller than --machines")
    opts = common.options_from(args)

    def run_site(o: common.Options) -> common.Section:
        return report(measure_site(o, args.machines, args.baseline, args.mode), args.mode)

    with common.interrupts_as_exceptions():
        common.save(common.measure(run_site, opts, common.command_line("bench.site", argv)), opts)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
