"""The machines as Prometheus metrics, read from the gateway's views at each scrape.

Names follow Prometheus' conventions: a `ride_machine_` prefix, base units (seconds), `_total`
for counters, one label `machine` (plus `state`, `code`, `axis` or `quantile` where a metric has
several series). docs/plant.md lists them; docs/plant-alerts.yml alerts on them.

A counter is there, at 0, from a machine's first sight (for every code it can count), so
`increase()` sees its first step. A machine that is gone keeps only `ride_machine_alive 0` and
the time of the status it was last heard with: the series that say how it is (state, E-stop,
fault, cycle timing) go, so Prometheus marks them stale and the alerts on them resolve
(`RideMachineGone` fires instead) rather than firing on a state nobody knows any more.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from ride_machine.schema.commands import ReplyCode
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MachineState

from .model import MachineView

COMMAND_CODES: tuple[str, ...] = tuple(c.value for c in ReplyCode) + tuple(
    e.value for e in ErrorCode
)
"""Every code a command's reply can carry: each machine's command counters start at 0 for all."""


@dataclass(frozen=True)
class GatewayStats:
    """The gateway's own counters, for its metrics."""

    machines: int
    opcua_sessions: int
    supervising: int
    updates_dropped: int
    version: str = "unknown"


class MachineCollector(Collector):
    """A custom collector: the views as they are at scrape time, no copy kept per update."""

    def __init__(
        self,
        views: Callable[[], list[MachineView]],
        stats: Callable[[], GatewayStats],
    ) -> None:
        self._views = views
        self._stats = stats

    def describe(self) -> list[Metric]:
        return []  # unchecked registration: the series come and go with the machines

    def collect(self) -> Iterator[Metric]:
        views = self._views()
        yield from _presence(views)
        yield from _state(views)
        yield from _cycle(views)
        yield from _events(views)
        yield from _gateway(self._stats())


def _gauge(name: str, doc: str, labels: tuple[str, ...] = ("machine",)) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, doc, labels=list(labels))


def _summary(name: str, doc: str) -> Metric:
    """A summary whose quantiles the machine computed (prometheus_client's own family takes
    only a count and a sum)."""
    return Metric(name, doc, "summary")


def _counter(name: str, doc: str, labels: tuple[str, ...] = ("machine",)) -> CounterMetricFamily:
    return CounterMetricFamily(name, doc, labels=list(labels))


def _presence(views: list[MachineView]) -> Iterator[Metric]:
    alive = _gauge("ride_machine_alive", "1 while the machine's liveliness token is present")
    uptime = _gauge("ride_machine_uptime_seconds", "Seconds since the daemon started")
    seen = _gauge(
        "ride_machine_status_timestamp_seconds",
        "The machine's time of its latest status publication (Unix seconds)",
    )
    build = _gauge(
        "ride_machine_build_info",
        "1, with the wire schema version the machine speaks",
        ("machine", "schema_version"),
    )
    for v in views:
        alive.add_metric([v.machine_id], 1.0 if v.alive else 0.0)
        if v.status is not None:
            seen.add_metric([v.machine_id], v.status.time)
            build.add_metric([v.machine_id, str(v.status.schema_version)], 1.0)
            if v.alive:
                uptime.add_metric([v.machine_id], v.status.uptime_s)
    yield from (alive, uptime, seen, build)


def _state(views: list[MachineView]) -> Iterator[Metric]:
    state = _gauge(
        "ride_machine_state",
        "1 for the machine's current state, 0 for the others",
        ("machine", "state"),
    )
    fault = _gauge("ride_machine_fault", "1 while a fault is active, by code", ("machine", "code"))
    estop = _gauge("ride_machine_estop_active", "1 while the E-stop input is pressed")
    latched = _gauge("ride_machine_estop_latched", "1 while the E-stop latch is set")
    rider = _gauge("ride_machine_rider_connected", "1 while the controlling Rider is present")
    storage = _gauge(
        "ride_machine_storage_warnings", "Status warnings about writes to the data directory"
    )
    flags = {
        "calibrated": _gauge(
            "ride_machine_calibrated", "1 if the axis is calibrated", ("machine", "axis")
        ),
        "homed": _gauge("ride_machine_homed", "1 if the axis is homed", ("machine", "axis")),
    }
    for v in views:
        s, mid = v.status, v.machine_id
        if s is None or not v.alive:
            continue
        for name in MachineState:
            state.add_metric([mid, name.value], 1.0 if s.state is name else 0.0)
        if s.fault is not None:
            fault.add_metric([mid, str(s.fault.code)], 1.0)
        estop.add_metric([mid], float(s.estop.active))
        latched.add_metric([mid], float(s.estop.latched))
        rider.add_metric([mid], float(s.rider_connected))
        storage.add_metric([mid], float(v.storage_warnings))
        for attr, family in flags.items():
            axes = getattr(s, attr)
            for axis in ("tilt", "rotate"):
                family.add_metric([mid, axis], float(getattr(axes, axis)))
    yield from (state, fault, estop, latched, rider, storage, *flags.values())


def _cycle(views: list[MachineView]) -> Iterator[Metric]:
    # The machine measures the percentiles over its recent window of cycles: summaries with
    # those quantiles and the count of cycles observed (no sum: the machine keeps none).
    window = "over the machine's recent window of cycles (quantiles); cycles run (count)"
    execution = Metric(
        "ride_machine_cycle_execution_seconds", f"Execution time {window}", "summary"
    )
    jitter = Metric("ride_machine_cycle_jitter_seconds", f"Wake-up jitter {window}", "summary")
    longest = _gauge("ride_machine_cycle_execution_max_seconds", "Longest execution since reset")
    period = _gauge("ride_machine_cycle_period_seconds", "The scan period configured")
    cycles = _counter("ride_machine_cycles", "Scan cycles run")
    overruns = _counter("ride_machine_overruns", "Cycles that overran their period (resettable)")
    missed = _counter("ride_machine_missed_cycles", "Deadlines skipped after overruns")
    for v in views:
        d, mid = v.diag, v.machine_id
        if d is None or not v.alive:
            continue
        for family, stats in ((execution, d.execution), (jitter, d.jitter)):
            for quantile, value in (("0.5", stats.p50), ("0.99", stats.p99)):
                family.add_sample(family.name, {"machine": mid, "quantile": quantile}, value)
            family.add_sample(f"{family.name}_count", {"machine": mid}, float(d.cycles))
        longest.add_metric([mid], d.execution.max)
        period.add_metric([mid], d.period_s)
        cycles.add_metric([mid], float(d.cycles))
        overruns.add_metric([mid], float(d.overruns))
        missed.add_metric([mid], float(d.missed_cycles))
    yield from (execution, jitter, longest, period, cycles, overruns, missed)


def _events(views: list[MachineView]) -> Iterator[Metric]:
    commands = _counter(
        "ride_machine_commands",
        "Commands answered since the gateway started, by reply code",
        ("machine", "code"),
    )
    written = _counter("ride_machine_events_written", "Events written to the machine's history")
    lost = _counter("ride_machine_events_lost", "Events lost: dropped (queue full) or not written")
    failures = _counter("ride_machine_storage_failures", "Writes of the event history that failed")
    for v in views:
        mid = v.machine_id
        counts = {code: 0 for code in COMMAND_CODES} | dict(v.commands)
        for code, n in sorted(counts.items()):
            commands.add_metric([mid, code], float(n))
        events = v.diag.events if v.diag is not None else None
        if events is not None:
            written.add_metric([mid], float(events.written))
            lost.add_metric([mid], float(events.lost + events.dropped))
            failures.add_metric([mid], float(events.failures))
    yield from (commands, written, lost, failures)


def _gateway(stats: GatewayStats) -> Iterator[Metric]:
    build = _gauge("ride_gateway_build_info", "1, with the gateway's version", ("version",))
    build.add_metric([stats.version], 1.0)
    yield build
    yield GaugeMetricFamily(
        "ride_gateway_machines", "Machines the gateway follows", value=stats.machines
    )
    yield GaugeMetricFamily(
        "ride_gateway_opcua_sessions", "OPC UA sessions open", value=stats.opcua_sessions
    )
    yield GaugeMetricFamily(
        "ride_gateway_opcua_supervising",
        "OPC UA sessions holding a Rider's supervision (they commanded)",
        value=stats.supervising,
    )
    yield CounterMetricFamily(
        "ride_gateway_updates_dropped",
        "Publications dropped: the gateway fell behind",
        value=stats.updates_dropped,
    )
