"""Status latency: publish in the daemon → receipt in a Rider process, on one host.

Each `Status` carries `time`, the wall-clock start of the cycle that built it; the Rider's
subscriber callback notes the wall clock on arrival (both processes read the same clock).
Two sources: a status every cycle (heartbeat shorter than the period), and status changes
triggered by E-stop presses/releases through `sim/estop` with the project's default config.
"""

from __future__ import annotations

import contextlib
import random
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import zenoh

from bench.common import Dist, Options, Section, Table, Target, main_for, ms, share
from bench.daemon import bench_daemon
from ride_machine.rider.client import Rider
from ride_machine.schema.codec import Format, decode
from ride_machine.schema.status import Status


@dataclass
class Arrivals:
    """(arrival wall time, payload) of every status, noted first thing in the callback."""

    items: list[tuple[float, bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: zenoh.Sample) -> None:
        now = time.time()
        data = sample.payload.to_bytes()
        with self.lock:
            self.items.append((now, data))

    def latencies(self) -> tuple[list[float], list[Status]]:
        with self.lock:
            items = list(self.items)
        statuses = []
        out = []
        for arrived, data in items:
            status = decode(Status, data, Format.MSGPACK)
            assert isinstance(status, Status)
            statuses.append(status)
            out.append(arrived - status.time)
        return out, statuses


@dataclass(frozen=True)
class Measured:
    label: str
    period_s: float
    latency: Dist
    exec_p50: float
    negative: int


@contextlib.contextmanager
def _watched(period_s: float, heartbeat_s: float | None) -> Iterator[tuple[Rider, Arrivals]]:
    """A daemon, a Rider noting every status's arrival, and the daemon's diag reset."""
    with contextlib.ExitStack() as stack:
        daemon = stack.enter_context(bench_daemon(period_s, heartbeat_s=heartbeat_s))
        rider = stack.enter_context(daemon.rider(supervise=False))
        arrivals = Arrivals()
        sub = rider.session.declare_subscriber(f"{rider.base}/status", arrivals.on_sample)
        stack.callback(sub.undeclare)
        rider.diag(reset=True)
        yield rider, arrivals


def _measured(label: str, period_s: float, latencies: list[float], exec_p50: float) -> Measured:
    negative = sum(x < 0 for x in latencies)
    return Measured(label, period_s, Dist.of(latencies), exec_p50, negative)


def every_cycle(period_s: float, seconds: float) -> Measured:
    """A status every cycle: heartbeat set below the period."""
    with _watched(period_s, period_s / 2) as (rider, arrivals):
        time.sleep(seconds)
        exec_p50 = rider.diag().execution.p50
    lat, _ = arrivals.latencies()
    return _measured(f"a status every cycle, {period_s * 1e3:g} ms", period_s, lat, exec_p50)


def on_change(period_s: float, changes: int, seed: int = 4) -> Measured:
    """Status changes triggered by E-stop presses and releases, default publication config."""
    rng = random.Random(seed)
    with _watched(period_s, None) as (rider, arrivals):
        for i in range(changes):
            rider.sim("estop", pressed=i % 2 == 0)
            time.sleep(rng.uniform(2 * period_s, 5 * period_s))
        rider.sim("estop", pressed=False)
        exec_p50 = rider.diag().execution.p50
    lat, statuses = arrivals.latencies()
    # Only statuses caused by a change: the E-stop flag differs from the previous status.
    changed = [
        x
        for x, prev, cur in zip(lat[1:], statuses[:-1], statuses[1:], strict=True)
        if cur.estop != prev.estop
    ]
    label = f"on change (E-stop toggles), {period_s * 1e3:g} ms"
    return _measured(label, period_s, changed, exec_p50)


def run(opts: Options) -> Section:
    section = Section("status_latency", "4. Status latency")
    results = [
        every_cycle(0.010, opts.pick(1.0, 15.0, 120.0)),
        on_change(0.010, opts.pick(10, 200, 2000)),
        every_cycle(0.001, opts.pick(0.5, 5.0, 30.0)),
    ]
    table = Table(
        "Cycle start in the daemon → status received by a Rider process (tcp/127.0.0.1)",
        ["source", "n", "p50 ms", "p90 ms", "p99 ms", "max ms", "p99 of period", "scan exec p50"],
        note="measured from the cycle's start, so it includes the scan's own work before it"
        " publishes (exec p50 shown); wall clocks of one host",
    )
    for m in results:
        d = m.latency
        table.add(
            m.label,
            d.n,
            ms(d.p50),
            ms(d.p90),
            ms(d.p99),
            ms(d.max),
            share(d.p99, m.period_s),
            ms(m.exec_p50),
        )
        section.targets.append(
            Target.at_most(
                f"status p99, {m.label}", d.p99, 0.10 * m.period_s, lambda x: f"{ms(x)} ms"
            )
        )
    section.tables.append(table)
    negative = sum(m.negative for m in results)
    if negative:
        section.notes.append(f"{negative} samples arrived 'before' their stamp: clock steps.")
    section.notes.append(
        "The status publisher is declared express with DATA_HIGH priority and drops rather"
        " than blocks under congestion."
    )
    return section


if __name__ == "__main__":
    sys.exit(main_for("bench.status_latency", __doc__ or "", run))
