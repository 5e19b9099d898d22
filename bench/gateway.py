"""The plant gateway under ten machines and twenty SCADA clients: how fast a status reaches the
OPC UA clients and a Prometheus scrape, what the gateway costs, and whether the machines' scan
loops notice it.

Ten `machine run --sim` daemons (10 ms period, a status every 50 ms each: 200 statuses/s in
all) and one `rider gateway` process connected to all of them, on this host:

- OPC UA: 20 asyncua clients (in 4 processes of 5) each subscribe to 40 items, 4 of every
  machine (`StatusSeq`, `Uptime`, `TiltPosition`, `Diagnostics/Cycles`): 800 monitored items;
  latency = the client's wall clock at a `StatusSeq` data-change notification (a new value
  with every status) − the status's `time` (the machine's clock at the start of the cycle that
  built it; one host, one clock). The clients share the host's two cores with everything else,
  so their own work is in the figure;
- Prometheus: the metrics endpoint is read every `SCRAPE_S`; latency = when a machine's
  `ride_machine_status_timestamp_seconds` first shows a new status − that status's `time`
  (bounded below by the polling: half a poll interval on average);
- the gateway's CPU (share of one core) and RSS over each phase;
- the daemons' loop timing (execution and wake-up jitter, from their `diag/cycle`, median over
  the ten) with no gateway, with it serving the OPC UA client, then without it again.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Client, ua

from bench.common import (
    Dist,
    Options,
    Section,
    Table,
    Target,
    cpu_seconds,
    main_or_child,
    ms,
    rss_bytes,
)
from bench.daemon import Tuning, config_toml
from ride_machine.schema.diag import CycleDiag
from tests.procs import REPO, Daemon, free_port, start_daemon, stop_process, write_zenoh_config

MACHINES = 10
PERIOD_S = 0.010
HEARTBEAT_S = 0.050
SCRAPE_S = 0.020
PUBLISH_MS = 10.0
"""The OPC UA subscription's requested publishing interval."""
NAMESPACE = "urn:ride-machine:gateway"
CLIENTS = 20
CLIENT_PROCESSES = 4
WATCHED = ("StatusSeq", "Uptime", "TiltPosition", "Diagnostics/Cycles")
"""Each client's items on every machine: 4 × 10 machines = 40 items a client."""
RSS_TARGET = 100 * 10**6
"""Issues 56 and 59: the gateway at 151 MB with ten machines; at most 100 MB (95.4 MiB)."""
_STAMP = re.compile(r'^ride_machine_status_timestamp_seconds\{machine="([^"]+)"\} (\S+)$', re.M)


@dataclass(frozen=True)
class Timing:
    """The ten daemons' loop timing over one phase (median of the per-daemon values)."""

    label: str
    exec_p50: float
    exec_p99: float
    jitter_p99: float
    overruns: int
    missed: int


@dataclass(frozen=True)
class Cost:
    label: str
    cpu_share: float
    """Gateway CPU seconds per wall second (1.0 = one core)."""
    rss: int


@contextlib.contextmanager
def machines(tmp: Path, count: int) -> Iterator[list[Daemon]]:
    """`count` daemons, each on its own loopback port; stopped (bounded) on exit."""
    config = tmp / "machine.toml"
    config.write_text(config_toml(PERIOD_S, Tuning(), HEARTBEAT_S, watchdog_periods=100))
    with contextlib.ExitStack() as stack:
        daemons = []
        for i in range(count):
            daemon = start_daemon(tmp, f"g{i:02d}", extra=["--config", str(config)])
            stack.callback(daemon.stop)
            daemons.append(daemon)
        yield daemons


@contextlib.contextmanager
def gateway(
    tmp: Path, daemons: list[Daemon], *more: str
) -> Iterator[tuple[subprocess.Popen[str], int, int]]:
    """`rider gateway` on every daemon's endpoint, its cache in `tmp` (made at its first start);
    (process, OPC UA port, metrics port) once it shows all ten machines."""
    opcua, metrics = free_port(), free_port()
    cmd = [
        sys.executable,
        "-m",
        "ride_machine.rider.cli",
        "--zenoh-config",
        str(write_zenoh_config(tmp)),
    ]
    for d in daemons:
        cmd += ["--connect", d.endpoint]
    cmd += ["gateway", "--opcua", f"127.0.0.1:{opcua}", "--metrics", f"127.0.0.1:{metrics}"]
    cmd += ["--log-level", "warning", "--cache-dir", str(tmp / "cache"), *more]
    log = (tmp / "gateway.log").open("w")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    try:
        deadline = time.monotonic() + 60
        while len(_stamps(_scrape(metrics))) < len(daemons):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError(f"gateway not serving: {(tmp / 'gateway.log').read_text()}")
            time.sleep(0.1)
        yield proc, opcua, metrics
    finally:
        stop_process(proc)
        log.close()


def _scrape(port: int) -> str:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
            return str(r.read().decode())
    except OSError:
        return ""


def _stamps(text: str) -> dict[str, float]:
    return {mid: float(v) for mid, v in _STAMP.findall(text)}


async def _clients(port: int, ids: list[str], count: int, seconds: float) -> dict[str, Any]:
    """`count` clients, each subscribed to `WATCHED` on every machine; once all are, "ready" on
    stdout, then `seconds` of notifications: the StatusSeq latencies, the notifications, the
    revised publishing interval."""
    latencies: list[float] = []
    notified = [0]

    class Handler:
        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            notified[0] += 1
            if node.nodeid.Identifier.endswith("/StatusSeq"):
                source = data.monitored_item.Value.SourceTimestamp
                if source is not None:
                    latencies.append(time.time() - source.timestamp())

    revised = 0.0
    async with contextlib.AsyncExitStack() as stack:
        for _ in range(count):
            client = Client(f"opc.tcp://127.0.0.1:{port}/", timeout=30)
            await stack.enter_async_context(client)
            idx = await client.get_namespace_index(NAMESPACE)
            sub = await client.create_subscription(PUBLISH_MS, Handler())
            paths = [f"{mid}/{path}" for mid in ids for path in WATCHED]
            await sub.subscribe_data_change([client.get_node(ua.NodeId(p, idx)) for p in paths])
            revised = float(sub.parameters.RequestedPublishingInterval)
        print("ready", flush=True)
        await asyncio.sleep(1.0)  # the initial values arrive first: not publications
        latencies.clear()
        notified[0] = 0
        await asyncio.sleep(seconds)
    return {"latencies": latencies, "notified": notified[0], "revised": revised}


def client_child(argv: list[str]) -> int:
    """`python -m bench.gateway clients PORT COUNT SECONDS ID…`: one process of clients; its
    figures as one JSON line."""
    port, count, seconds, ids = int(argv[0]), int(argv[1]), float(argv[2]), argv[3:]
    logging.getLogger("asyncua").setLevel(logging.ERROR)  # its note on each revised timeout
    print(json.dumps(asyncio.run(_clients(port, ids, count, seconds))), flush=True)
    return 0


@contextlib.contextmanager
def client_processes(
    port: int, ids: list[str], clients: int, seconds: float
) -> Iterator[list[subprocess.Popen[str]]]:
    """The clients, `CLIENT_PROCESSES` processes of them, once every one has subscribed."""
    per = max(1, clients // CLIENT_PROCESSES)
    cmd = [sys.executable, "-m", "bench.gateway", "clients", str(port), str(per), str(seconds)]
    procs = [
        subprocess.Popen(
            [*cmd, *ids],
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        for _ in range(min(CLIENT_PROCESSES, clients))
    ]
    try:
        for proc in procs:
            assert proc.stdout is not None
            if proc.stdout.readline().strip() != "ready":
                raise RuntimeError("a client process did not subscribe")
        yield procs
    finally:
        for proc in procs:
            stop_process(proc)


def _results(procs: list[subprocess.Popen[str]], seconds: float) -> dict[str, Any]:
    got: dict[str, Any] = {"latencies": [], "notified": 0, "revised": 0.0}
    for proc in procs:
        out, _ = proc.communicate(timeout=seconds + 60)
        one = json.loads(out.strip().splitlines()[-1])
        got["latencies"] += one["latencies"]
        got["notified"] += one["notified"]
        got["revised"] = one["revised"]
    return got


def _scrape_latencies(port: int, seconds: float) -> list[float]:
    """Read the metrics every `SCRAPE_S`; the age of each new status when first seen."""
    last: dict[str, float] = {}
    out: list[float] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        text = _scrape(port)
        now = time.time()
        for mid, stamp in _stamps(text).items():
            if last.get(mid, stamp) != stamp:
                out.append(now - stamp)
            last[mid] = stamp
        time.sleep(SCRAPE_S)
    return out


def _timing(label: str, daemons: list[Daemon], seconds: float) -> Timing:
    """Reset every daemon's diagnostics, wait `seconds`, read them."""
    riders = [d.rider(supervise=False, timeout=5.0) for d in daemons]
    with contextlib.ExitStack() as stack:
        for r in riders:
            stack.enter_context(r).diag(reset=True)
        time.sleep(seconds)
        diags: list[CycleDiag] = [r.diag() for r in riders]
    return Timing(
        label,
        statistics.median(d.execution.p50 for d in diags),
        statistics.median(d.execution.p99 for d in diags),
        statistics.median(d.jitter.p99 for d in diags),
        sum(d.overruns for d in diags),
        sum(d.missed_cycles for d in diags),
    )


class _Sampler:
    """The gateway's CPU and RSS over a phase (RSS: the largest seen)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.rss = rss_bytes(pid)
        self._cpu = cpu_seconds(pid)
        self._t = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.wait(0.5):
            self.rss = max(self.rss, rss_bytes(self.pid))

    def done(self, label: str) -> Cost:
        self._stop.set()
        self._thread.join()
        share = (cpu_seconds(self.pid) - self._cpu) / (time.monotonic() - self._t)
        return Cost(label, share, max(self.rss, rss_bytes(self.pid)))


@dataclass(frozen=True)
class Measured:
    timings: list[Timing]
    costs: list[Cost]
    opc: Dist
    prom: Dist
    revised: float
    notified_per_s: float
    clients: int


def measure(seconds: float, count: int, clients: int) -> Measured:
    with tempfile.TemporaryDirectory(prefix="bench-gateway-") as name:
        tmp = Path(name)
        with machines(tmp, count) as daemons:
            ids = [d.machine_id for d in daemons]
            timings = [_timing("no gateway", daemons, seconds)]
            with gateway(tmp, daemons) as (proc, opcua, metrics):
                idle = _Sampler(proc.pid)
                timings.append(_timing("gateway, no client", daemons, seconds))
                costs = [idle.done(f"{count} machines, no client")]
                with client_processes(opcua, ids, clients, seconds) as procs:
                    sampler = _Sampler(proc.pid)
                    timings.append(_timing(f"gateway + {clients} OPC UA clients", daemons, seconds))
                    got = _results(procs, seconds)
                    items = clients * len(WATCHED) * count
                    costs.append(sampler.done(f"+ {clients} OPC UA clients, {items} items"))
                sampler = _Sampler(proc.pid)
                scraped = _scrape_latencies(metrics, seconds)
                costs.append(sampler.done(f"+ a scrape every {SCRAPE_S * 1e3:g} ms"))
            with gateway(tmp, daemons, "--no-cache") as (proc, _, _):
                idle = _Sampler(proc.pid)
                time.sleep(seconds)
                costs.append(idle.done(f"{count} machines, no client, --no-cache (as before)"))
            timings.append(_timing("no gateway again", daemons, seconds))
    return Measured(
        timings,
        costs,
        Dist.of(got["latencies"]),
        Dist.of(scraped),
        got["revised"],
        got["notified"] / seconds,
        clients,
    )


def run(opts: Options) -> Section:
    section = Section("gateway", "12. Plant gateway: OPC UA and Prometheus")
    seconds = opts.pick(1.0, 15.0, 60.0)
    count = opts.pick(3, MACHINES)  # the smoke run (tests/bench) starts fewer daemons
    got = measure(seconds, count, opts.pick(2, CLIENTS))
    opc, prom = got.opc, got.prom
    lat = Table(
        f"Status publication → client, {count} machines ({count / HEARTBEAT_S:g} statuses/s)",
        ["path", "n", "p50 ms", "p90 ms", "p99 ms", "max ms"],
        note="from the machine's clock at the start of the cycle that built the status, so it"
        " includes the daemon's own publication (section 4) and the clients' own work; wall"
        f" clocks of one host; the clients got {got.notified_per_s:.0f} notifications/s in all",
    )
    lat.add(
        f"OPC UA data change, {got.clients} clients × {len(WATCHED) * count} items"
        f" (publishing interval {got.revised:g} ms)",
        opc.n,
        ms(opc.p50),
        ms(opc.p90),
        ms(opc.p99),
        ms(opc.max),
    )
    lat.add(
        f"Prometheus scrape value (read every {SCRAPE_S * 1e3:g} ms)",
        prom.n,
        ms(prom.p50),
        ms(prom.p90),
        ms(prom.p99),
        ms(prom.max),
    )
    cost = Table("The gateway process", ["phase", "CPU (share of one core)", "RSS MiB"])
    for c in got.costs:
        cost.add(c.label, f"{100 * c.cpu_share:.1f} %", f"{c.rss / 2**20:.1f}")
    loop = Table(
        f"The {count} daemons' scan loops (median over the daemons; {seconds:g} s a phase)",
        ["phase", "exec p50 ms", "exec p99 ms", "jitter p99 ms", "overruns", "missed"],
    )
    timings = got.timings
    for t in timings:
        loop.add(t.label, ms(t.exec_p50), ms(t.exec_p99), ms(t.jitter_p99), t.overruns, t.missed)
    section.tables += [lat, cost, loop]
    off = statistics.median([timings[0].exec_p50, timings[-1].exec_p50])
    on = timings[2].exec_p50
    section.targets.append(
        Target.at_most(
            "daemons' exec p50 with the gateway vs without", on, off * 1.2, lambda x: f"{ms(x)} ms"
        )
    )
    section.targets.append(
        Target.at_most(
            "gateway RSS, most of any phase with its cache",
            max(c.rss for c in got.costs if "--no-cache" not in c.label),
            RSS_TARGET,
            lambda x: f"{x / 2**20:.1f} MiB",
        )
    )
    section.notes.append(
        "The gateway is a separate process (a Zenoh peer like any Rider): what the daemons see"
        " of it is one more subscriber per publication and its share of the host's two cores;"
        " the exec columns are the daemons' own work, jitter is where CPU contention shows."
    )
    section.notes.append(
        "The gateway reads the OPC UA standard nodes from its cache (rider/gateway/"
        "nodeset_cache.py) instead of holding all ~6,000 in memory: about 50 MB less RSS."
    )
    return section


if __name__ == "__main__":
    sys.exit(main_or_child("bench.gateway", __doc__ or "", run, None, {"clients": client_child}))
