"""The plant gateway under ten machines: how fast a status reaches an OPC UA client and a
Prometheus scrape, what the gateway costs, and whether the machines' scan loops notice it.

Ten `machine run --sim` daemons (10 ms period, a status every 50 ms each: 200 statuses/s in
all) and one `rider gateway` process connected to all of them, on this host:

- OPC UA: an asyncua client subscribes to every machine's `StatusSeq` (a new value with every
  status); latency = the client's wall clock at the data-change notification − the status's
  `time` (the machine's clock at the start of the cycle that built it; one host, one clock);
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

from bench.common import Dist, Options, Section, Table, Target, cpu_seconds, main_for, ms, rss_bytes
from bench.daemon import Tuning, config_toml
from schema.diag import CycleDiag
from tests.procs import REPO, Daemon, free_port, start_daemon, stop_process, write_zenoh_config

MACHINES = 10
PERIOD_S = 0.010
HEARTBEAT_S = 0.050
SCRAPE_S = 0.020
PUBLISH_MS = 10.0
"""The OPC UA subscription's requested publishing interval."""
NAMESPACE = "urn:ride-machine:gateway"
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
def gateway(tmp: Path, daemons: list[Daemon]) -> Iterator[tuple[subprocess.Popen[str], int, int]]:
    """`rider gateway` on every daemon's endpoint; (process, OPC UA port, metrics port) once it
    shows all ten machines."""
    opcua, metrics = free_port(), free_port()
    cmd = [sys.executable, "-m", "rider.cli", "--zenoh-config", str(write_zenoh_config(tmp))]
    for d in daemons:
        cmd += ["--connect", d.endpoint]
    cmd += ["gateway", "--opcua", f"127.0.0.1:{opcua}", "--metrics", f"127.0.0.1:{metrics}"]
    cmd += ["--log-level", "warning"]
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


async def _opcua_latencies(port: int, ids: list[str], seconds: float) -> tuple[list[float], float]:
    """Every StatusSeq data change's latency over `seconds`; and the revised interval."""
    latencies: list[float] = []

    class Handler:
        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            now = time.time()
            source = data.monitored_item.Value.SourceTimestamp
            if source is not None:
                latencies.append(now - source.timestamp())

    client = Client(f"opc.tcp://127.0.0.1:{port}/", timeout=10)
    async with client:
        idx = await client.get_namespace_index(NAMESPACE)
        sub = await client.create_subscription(PUBLISH_MS, Handler())
        nodes = [client.get_node(ua.NodeId(f"{mid}/StatusSeq", idx)) for mid in ids]
        await sub.subscribe_data_change(nodes)
        await asyncio.sleep(0.5)  # the initial values arrive first: not publications
        latencies.clear()
        await asyncio.sleep(seconds)
        revised = float(sub.parameters.RequestedPublishingInterval)
    return latencies, revised


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


def measure(seconds: float, count: int) -> tuple[list[Timing], list[Cost], Dist, Dist, float]:
    with tempfile.TemporaryDirectory(prefix="bench-gateway-") as name:
        tmp = Path(name)
        with machines(tmp, count) as daemons:
            ids = [d.machine_id for d in daemons]
            timings = [_timing("no gateway", daemons, seconds)]
            with gateway(tmp, daemons) as (proc, opcua, metrics):
                idle = _Sampler(proc.pid)
                timings.append(_timing("gateway, no client", daemons, seconds))
                costs = [idle.done("10 machines, no client")]
                sampler = _Sampler(proc.pid)
                holder: dict[str, Any] = {}
                worker = threading.Thread(
                    target=lambda: holder.update(
                        opc=asyncio.run(_opcua_latencies(opcua, ids, seconds))
                    )
                )
                worker.start()
                timings.append(_timing("gateway + OPC UA client", daemons, seconds))
                worker.join()
                costs.append(sampler.done("+ OPC UA client on all 10"))
                sampler = _Sampler(proc.pid)
                scraped = _scrape_latencies(metrics, seconds)
                costs.append(sampler.done(f"+ a scrape every {SCRAPE_S * 1e3:g} ms"))
            timings.append(_timing("no gateway again", daemons, seconds))
    opc_latencies, revised = holder["opc"]
    return timings, costs, Dist.of(opc_latencies), Dist.of(scraped), revised


def run(opts: Options) -> Section:
    section = Section("gateway", "12. Plant gateway: OPC UA and Prometheus")
    seconds = opts.pick(1.0, 15.0, 60.0)
    count = opts.pick(3, MACHINES)  # the smoke run (tests/bench) starts fewer daemons
    timings, costs, opc, prom, revised = measure(seconds, count)
    lat = Table(
        f"Status publication → client, {count} machines ({count / HEARTBEAT_S:g} statuses/s)",
        ["path", "n", "p50 ms", "p90 ms", "p99 ms", "max ms"],
        note="from the machine's clock at the start of the cycle that built the status, so it"
        " includes the daemon's own publication (section 4); wall clocks of one host",
    )
    lat.add(
        f"OPC UA data change (publishing interval {revised:g} ms)",
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
    for c in costs:
        cost.add(
            c.label.replace("10", str(count)), f"{100 * c.cpu_share:.1f} %", f"{c.rss / 2**20:.0f}"
        )
    loop = Table(
        f"The {count} daemons' scan loops (median over the daemons; {seconds:g} s a phase)",
        ["phase", "exec p50 ms", "exec p99 ms", "jitter p99 ms", "overruns", "missed"],
    )
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
    section.notes.append(
        "The gateway is a separate process (a Zenoh peer like any Rider): what the daemons see"
        " of it is one more subscriber per publication and its share of the host's two cores;"
        " the exec columns are the daemons' own work, jitter is where CPU contention shows."
    )
    return section


if __name__ == "__main__":
    sys.exit(main_for("bench.gateway", __doc__ or "", run))
