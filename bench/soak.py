"""Soak: the supervised machine under a command storm, rides, E-stops and Riders coming and going.

`python -m bench.soak [--minutes 10]` runs `machine supervise --sim` (fast mechanics) and, for
the whole duration and all at once:
- a command storm: several Riders sending read-only commands, malformed commands and reads at a
  steady rate, each reply timed and every request without a reply counted as missed;
- rides: an operator Rider homes and runs short sessions back to back, and every so often
  presses the E-stop mid-ride (through the simulated world), checks the relays dropped,
  releases it and homes again;
- churn: a Rider that connects, reads the status and disconnects, over and over.
The daemon's and the supervisor's resident memory is sampled throughout, and the daemon's own
cycle diagnostics (overruns, missed cycles) are read at the start and the end. Then a few
SIGKILLs of the daemon mid-ride measure the supervisor's reaction and the restart.
Results are printed and written to the `soak` section of BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from bench.common import (
    Dist,
    Section,
    Table,
    command_line,
    growth_per_hour,
    measure_and_save,
    mib,
    ms,
    rss_bytes,
    soak_parser,
    tenths,
)
from ride_machine.rider.client import CommandRefused, MachineTimeout, Rider, RiderError
from ride_machine.schema.codec import Format, decode, pack
from ride_machine.schema.commands import REST_STATES, Command, Reply, RotateStep, Session, TiltStep
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.status import FAULT_STATES, FaultCode, MachineState, Status
from tests.integration.support import raw_get
from tests.procs import Daemon
from tests.reliability.support import StatusFeed, start_machine, supervisor_child

SETTLED = REST_STATES | FAULT_STATES
RIDE = Session(name="soak", steps=[TiltStep(degrees=25.0), RotateStep(revolutions=3)])
REPLY_TIMEOUT_S = 2.0
STEP_TIMEOUT_S = 30.0
SAMPLE_EVERY_S = 5.0
RELAYS_OFF_BOUND_S = 0.5
WARMUP_S = 20.0
"""Memory samples before this are left out of the growth figures (imports, caches, pools)."""


STORM_RIDERS = 4
ESTOP_EVERY_S = 20.0
CHURN_EVERY_S = 0.5


@dataclass(frozen=True)
class SoakOptions:
    """What the command line sets (its defaults: `build_parser`)."""

    minutes: float
    rate: float
    """Storm requests per second, over all storm Riders."""
    kills: int
    out: Path | None


# ----------------------------------------------------------------------------- tallies
@dataclass
class Tally:
    """Thread-safe counts and latencies of one kind of traffic."""

    sent: int = 0
    answered: int = 0
    missed: int = 0
    refused: Counter[str] = field(default_factory=Counter)
    latency_s: list[float] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def record(self, started: float, outcome: str | None) -> None:
        """`outcome`: None answered, "missed" for no reply, else the refusal code."""
        elapsed = time.perf_counter() - started
        with self.lock:
            self.sent += 1
            if outcome == "missed":
                self.missed += 1
                return
            self.answered += 1
            self.latency_s.append(elapsed)
            if outcome is not None:
                self.refused[outcome] += 1


def _raw_command(rider: Rider, suffix: str, payload: bytes) -> None:
    """One command query outside the typed client; raises like `Rider.command` does."""
    replies = raw_get(rider, f"cmd/{suffix}", payload, Format.MSGPACK, REPLY_TIMEOUT_S)
    if not replies:
        raise MachineTimeout(f"no reply from cmd/{suffix}")
    sample = replies[0].ok if replies[0].ok is not None else replies[0].err
    assert sample is not None
    fmt = Format.JSON if str(sample.encoding).startswith(Format.JSON) else Format.MSGPACK
    reply = decode(Reply, sample.payload.to_bytes(), fmt)
    if not reply.success:
        raise CommandRefused(reply)


def _storm_requests(rider: Rider) -> list[Callable[[], object]]:
    """Requests that never move the machine: checks, reads, malformed and unknown commands."""
    return [
        lambda: rider.command(Command.CHECK_CALIBRATION),
        lambda: rider.command(Command.CHECK_HOME),
        rider.status,
        rider.diag,
        rider.io,
        rider.params,
        lambda: _raw_command(rider, "home", pack({"transaction_id": 7})),
        lambda: _raw_command(rider, "launch", pack({"transaction_id": rider.new_transaction_id()})),
    ]


def storm_worker(daemon: Daemon, tally: Tally, rate: float, stop: threading.Event) -> None:
    with daemon.rider(timeout=REPLY_TIMEOUT_S, retries=0, supervise=False) as rider:
        requests = _storm_requests(rider)
        period = 1.0 / rate
        due = time.monotonic()
        n = 0
        while not stop.is_set():
            request = requests[n % len(requests)]
            n += 1
            started = time.perf_counter()
            try:
                request()
                tally.record(started, None)
            except CommandRefused as exc:
                tally.record(started, str(exc.error.code))
            except MachineTimeout:
                tally.record(started, "missed")
            due += period
            delay = due - time.monotonic()
            if delay < -1.0:
                due = time.monotonic()  # fell far behind: do not burst
            stop.wait(max(0.0, delay))


# --------------------------------------------------------------------------------- rides
@dataclass
class Rides:
    done: int = 0
    faults: Counter[str] = field(default_factory=Counter)
    estops: int = 0
    estop_s: list[float] = field(default_factory=list)
    """E-stop pressed in the world → FAULT_ESTOP status received."""
    estop_world_s: list[float] = field(default_factory=list)
    """E-stop pressed → the world's relays seen off."""
    estop_relays_on_after: int = 0
    """E-stops after which the world still had a relay on after `RELAYS_OFF_BOUND_S`."""
    errors: list[str] = field(default_factory=list)


def _settle(feed: StatusFeed, reply: Reply) -> Status:
    return feed.until(
        lambda s: s.time >= reply.timecode and s.state in SETTLED, timeout=STEP_TIMEOUT_S
    )


def _estop_mid_ride(r: Rider, feed: StatusFeed, out: Rides) -> None:
    reply = r.start(RIDE)
    feed.until(
        lambda s: s.time >= reply.timecode and s.state is MachineState.RUNNING,
        timeout=STEP_TIMEOUT_S,
    )
    pressed = time.monotonic()
    r.sim("estop", pressed=True)
    feed.until(lambda s: s.state is MachineState.FAULT_ESTOP, timeout=STEP_TIMEOUT_S)
    out.estop_s.append(time.monotonic() - pressed)
    out.estops += 1
    # The world samples the relays every few ms: ask until it has seen them drop (bounded).
    deadline = time.monotonic() + RELAYS_OFF_BOUND_S
    while any(r.sim("world").relays.values()):
        if time.monotonic() > deadline:
            out.estop_relays_on_after += 1
            break
    else:
        out.estop_world_s.append(time.monotonic() - pressed)
    r.sim("estop", pressed=False)
    feed.until(lambda s: not s.estop.active, timeout=STEP_TIMEOUT_S)


def rides_worker(daemon: Daemon, out: Rides, estop_every_s: float, stop: threading.Event) -> None:
    with daemon.rider(timeout=REPLY_TIMEOUT_S) as r:
        feed = StatusFeed(r)
        last_estop = time.monotonic()
        try:
            while not stop.is_set():
                try:
                    status = r.status()
                    if not status.calibrated.tilt:
                        _settle(feed, r.calibrate_tilt())
                    if not status.calibrated.rotate:
                        _settle(feed, r.calibrate_rotate())
                    homed = _settle(feed, r.home())
                    if homed.state is not MachineState.IDLE:
                        out.faults[str(homed.fault.code if homed.fault else homed.state)] += 1
                        continue
                    if time.monotonic() - last_estop >= estop_every_s:
                        last_estop = time.monotonic()
                        _estop_mid_ride(r, feed, out)
                        continue
                    ended = _settle(feed, r.start(RIDE))
                    if ended.state is MachineState.DONE:
                        out.done += 1
                    else:
                        out.faults[str(ended.fault.code if ended.fault else ended.state)] += 1
                except (RiderError, AssertionError) as exc:
                    out.errors.append(f"{type(exc).__name__}: {exc}"[:200])
                    if len(out.errors) > 50:
                        raise
        finally:
            feed.close()


@dataclass
class Churn:
    cycles: int = 0
    failures: int = 0


def churn_worker(daemon: Daemon, out: Churn, every_s: float, stop: threading.Event) -> None:
    while not stop.wait(every_s):
        try:
            with daemon.rider(timeout=REPLY_TIMEOUT_S, retries=0) as r:
                r.status()
            out.cycles += 1
        except RiderError:
            out.failures += 1


# ------------------------------------------------------------------------------- memory
@dataclass
class Sample:
    t: float
    daemon_rss: int
    supervisor_rss: int


# --------------------------------------------------------------------------------- kills
@dataclass
class Kills:
    to_fault_s: list[float] = field(default_factory=list)
    to_restart_s: list[float] = field(default_factory=list)
    relays_on_after: int = 0


def kill_mid_ride(daemon: Daemon, n: int) -> Kills:
    out = Kills()
    with daemon.rider(timeout=REPLY_TIMEOUT_S) as r:
        feed = StatusFeed(r)
        try:
            for _ in range(n):
                status = r.status()
                if not (status.calibrated.tilt and status.calibrated.rotate):
                    _settle(feed, r.calibrate_tilt())
                    _settle(feed, r.calibrate_rotate())
                _settle(feed, r.home())
                reply = r.start(Session(name="long", steps=[RotateStep(revolutions=100)]))
                feed.until(
                    lambda s, t=reply.timecode: s.time >= t and s.state is MachineState.RUNNING
                )
                child = supervisor_child(daemon)
                killed = time.monotonic()
                os.kill(child, signal.SIGKILL)
                feed.until(_daemon_died)
                out.to_fault_s.append(time.monotonic() - killed)
                if any(r.sim("world").relays.values()):
                    out.relays_on_after += 1
                feed.until(lambda s: not _daemon_died(s))
                out.to_restart_s.append(time.monotonic() - killed)
        finally:
            feed.close()
    return out


def _daemon_died(s: Status) -> bool:
    return s.fault is not None and s.fault.code is FaultCode.DAEMON_DIED


# ----------------------------------------------------------------------------------- run
@contextlib.contextmanager
def supervised() -> Iterator[Daemon]:
    with tempfile.TemporaryDirectory(prefix="soak-") as tmp:
        daemon = start_machine(Path(tmp), command="supervise")
        try:
            yield daemon
        finally:
            daemon.stop()


def soak(opts: SoakOptions) -> Section:
    section = Section("soak", "Soak (bench/soak.py)")
    stop = threading.Event()
    storm, rides, churn, kills = Tally(), Rides(), Churn(), Kills()
    samples: list[Sample] = []
    with supervised() as daemon, daemon.rider(timeout=REPLY_TIMEOUT_S) as probe:
        child = supervisor_child(daemon)
        diag0 = probe.diag()
        workers = [
            threading.Thread(
                target=storm_worker,
                args=(daemon, storm, opts.rate / STORM_RIDERS, stop),
                name=f"storm-{i}",
            )
            for i in range(STORM_RIDERS)
        ]
        workers.append(
            threading.Thread(target=rides_worker, args=(daemon, rides, ESTOP_EVERY_S, stop))
        )
        workers.append(
            threading.Thread(target=churn_worker, args=(daemon, churn, CHURN_EVERY_S, stop))
        )
        t0 = time.monotonic()
        end = t0 + 60.0 * opts.minutes
        for w in workers:
            w.start()
        try:
            while not stop.wait(max(0.0, min(SAMPLE_EVERY_S, end - time.monotonic()))):
                t = time.monotonic() - t0
                samples.append(Sample(t, rss_bytes(child), rss_bytes(daemon.proc.pid, family=True)))
                if time.monotonic() >= end or not all(w.is_alive() for w in workers):
                    break
        finally:
            stop.set()
            for w in workers:
                w.join(timeout=STEP_TIMEOUT_S + REPLY_TIMEOUT_S)
        elapsed = time.monotonic() - t0
        diag1 = probe.diag()
        restarted = supervisor_child(daemon) != child
        if opts.kills:
            kills = kill_mid_ride(daemon, opts.kills)

    steady = [s for s in samples if s.t >= WARMUP_S] or samples
    section.tables += [
        traffic_table(storm, rides, churn, elapsed, opts),
        memory_table(samples, steady),
        rss_curve(samples),
        loop_table(diag0, diag1, restarted),
    ]
    if opts.kills:
        section.tables.append(kills_table(kills, opts.kills))
    section.notes.append(
        f"{opts.minutes:g} min of `machine supervise --sim` (fast mechanics) on loopback; the"
        " storm, the rides and the churn run at the same time in one bench process."
    )
    return section


def traffic_table(
    storm: Tally, rides: Rides, churn: Churn, elapsed: float, opts: SoakOptions
) -> Table:
    lat, estop = Dist.of(storm.latency_s), Dist.of(rides.estop_s)
    world = Dist.of(rides.estop_world_s)
    refused = ", ".join(f"{k} {v}" for k, v in storm.refused.most_common())
    faults = ", ".join(f"{k} {v}" for k, v in rides.faults.items()) or "no faults"
    t = Table("Traffic", ["what", "count", "detail"])
    t.add("storm requests", storm.sent, f"{storm.sent / elapsed:.0f}/s, {STORM_RIDERS} Riders")
    t.add("answered", storm.answered, f"p50 {ms(lat.p50)}, p99 {ms(lat.p99)}, max {ms(lat.max)} ms")
    t.add("**missed replies**", storm.missed, "requests with no reply within 2 s")
    t.add("refusals (expected)", sum(storm.refused.values()), refused)
    t.add("rides to DONE", rides.done, faults)
    t.add(
        "E-stops mid-ride",
        rides.estops,
        f"press → FAULT_ESTOP seen p50 {ms(estop.p50, 1)}, max {ms(estop.max, 1)} ms;"
        f" → world relays off p50 {ms(world.p50, 1)}, max {ms(world.max, 1)} ms;"
        f" still on after {RELAYS_OFF_BOUND_S:g} s: {rides.estop_relays_on_after}",
    )
    t.add("Rider connect/disconnect", churn.cycles, f"{churn.failures} failed")
    t.add("operator errors", len(rides.errors), "; ".join(rides.errors[:3]))
    return t


def memory_table(samples: list[Sample], steady: list[Sample]) -> Table:
    half = [s for s in steady if s.t >= (steady[0].t + steady[-1].t) / 2] or steady
    t = Table(
        "Memory (RSS)",
        ["process", "after warm-up MiB", "end MiB", "max MiB", "MiB/h", "MiB/h, 2nd half"],
    )
    for name, pick in (("daemon", _daemon_rss), ("supervisor", _supervisor_rss)):
        values = [pick(s) for s in steady]
        slope = growth_per_hour([s.t for s in steady], values)
        late = growth_per_hour([s.t for s in half], [pick(s) for s in half])
        t.add(
            name,
            mib(values[0]),
            mib(values[-1]),
            mib(max(values)),
            f"{slope / 2**20:+.1f}",
            f"{late / 2**20:+.1f}",
        )
    t.note = (
        f"{len(samples)} samples every {SAMPLE_EVERY_S:g} s; MiB/h = least-squares slope of"
        f" the samples after the first {WARMUP_S:g} s, and of the second half alone"
    )
    return t


def rss_curve(samples: list[Sample], rows: int = 10) -> Table:
    """RSS over time, a row per tenth of the run."""
    t = Table("RSS over time", ["minute", "daemon MiB", "supervisor MiB"])
    for s in (samples[i] for i in tenths(len(samples), rows)):
        t.add(f"{s.t / 60:.1f}", mib(s.daemon_rss), mib(s.supervisor_rss))
    return t


def _daemon_rss(s: Sample) -> int:
    return s.daemon_rss


def _supervisor_rss(s: Sample) -> int:
    return s.supervisor_rss


def loop_table(diag0: CycleDiag, diag1: CycleDiag, restarted: bool) -> Table:
    t = Table("Scan loop (the daemon's diag/cycle)", ["what", "value"])
    t.add("cycles", diag1.cycles - diag0.cycles)
    t.add("overruns", diag1.overruns - diag0.overruns)
    t.add("missed cycles", diag1.missed_cycles - diag0.missed_cycles)
    t.add("execution max", f"{ms(diag1.execution.max)} ms")
    t.add("daemon restarted during the soak", "yes" if restarted else "no")
    return t


def kills_table(kills: Kills, n: int) -> Table:
    f, r = Dist.of(kills.to_fault_s), Dist.of(kills.to_restart_s)
    t = Table("SIGKILL of the daemon mid-ride (supervisor)", ["what", "p50", "max"])
    t.add("kill → FAULT_HW status seen (ms)", ms(f.p50, 1), ms(f.max, 1))
    t.add("kill → restarted daemon's status (s)", f"{r.p50:.2f}", f"{r.max:.2f}")
    t.note = (
        f"{n} kills; world relays on after FAULT_HW: {kills.relays_on_after};"
        " restart back-off 0.5 s doubling"
    )
    return t


def build_parser() -> argparse.ArgumentParser:
    p = soak_parser("bench.soak", __doc__ or "", minutes=10.0)
    p.add_argument("--rate", type=float, default=200.0, help="storm requests per second")
    p.add_argument("--kills", type=int, default=3, help="SIGKILLs of the daemon at the end")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    if not 0 < args.minutes <= 24 * 60 or args.rate <= 0 or args.kills < 0:
        print("bench.soak: need 0 < --minutes <= 1440, --rate > 0, --kills >= 0", file=sys.stderr)
        return 2
    opts = SoakOptions(
        minutes=args.minutes,
        rate=args.rate,
        kills=args.kills,
        out=None if args.no_write else args.out,
    )
    measure_and_save(lambda: soak(opts), opts.out, command_line("bench.soak", argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
