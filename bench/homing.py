"""bench.homing: how far the positions the machine reports are from the truth, quiet and busy.

Real `machine run --sim` daemons, driven over Zenoh by a Rider each: every run puts the ride
somewhere new (`sim/place`: tilt −10°…60°, rotate anywhere), calibrates the tilt and the
rotate, homes, and runs a short session (the tilt to a random angle, one revolution). After
each calibration, Home and session the reported values (the calibration record, the axis
records) are compared with the simulator's truth (`sim/world`). The same runs on a quiet host
and beside two CPU-bound processes (bench/baselines/burner.py, one per core). Several daemons
run side by side to keep the wall time down (each is a few % of a core while moving); the
simulated ride has switch hysteresis and bounce and analog noise, the default speeds and the
default tolerances, and a watchdog relaxed as the tests' (the point is the latch, not the
watchdog). A measurement refused with a fault (an edge seen only across stalled scans, a
calibration that did not repeat) is counted as refused, never as an error.
"""

from __future__ import annotations

import random
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from bench.common import Dist, Options, Section, Table, Target, burners, main_for
from ride_machine.rider.client import CommandRefused, MachineTimeout, Rider
from ride_machine.schema.commands import REST_STATES, RotateStep, Session, TiltStep
from ride_machine.schema.status import FAULT_STATES, MachineState, Status
from tests.procs import Daemon, start_daemon

CONFIG = """\
[loop]
watchdog_periods = 100

[rider_loss]
timeout_s = 2.0

[events]
enabled = false   # not what this measures; ten daemons need no ten history processes

[hal.sim]
tilt_min_deg = -12.0
tilt_home_hysteresis_deg = 0.5
rotate_home_hysteresis_deg = 0.2
tilt_home_bounce_s = 0.002
tilt_noise_counts = 2.0
"""
ENDED = REST_STATES | FAULT_STATES
STEP_TIMEOUT_S = 120.0
OFFSET_TOL_DEG = 0.25
POSITION_TOL_DEG = 0.5


@dataclass
class Errors:
    """Errors against the truth, in degrees, and how the measurements ended."""

    offset: list[float] = field(default_factory=list)
    tilt: list[float] = field(default_factory=list)
    rotate: list[float] = field(default_factory=list)
    outcomes: Counter[str] = field(default_factory=Counter)
    failures: list[Exception] = field(default_factory=list)
    """What ended a daemon's runs early (a benchmark that cannot run says so)."""
    daemons: list[Daemon] = field(default_factory=list)
    """Every daemon started, so an interrupted benchmark stops them all."""
    stop: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, what: str, value: float) -> None:
        with self.lock:
            getattr(self, what).append(value)

    def ended(self, what: str, status: Status) -> bool:
        fault = status.fault
        key = f"{what} DONE" if fault is None else f"{what} {fault.code}"
        with self.lock:
            self.outcomes[key] += 1
        return fault is None and status.state is not MachineState.FAULT_HW


def _wrap(delta: float) -> float:
    return abs((delta + 180.0) % 360.0 - 180.0)


def _positions(r: Rider, errors: Errors) -> None:
    """The axis records (unrounded) against the world, both at rest."""
    world = r.sim("world")
    axes = {a.axis: a for a in r.axes()}
    tilt, rotate = axes["tilt"], axes["rotate"]
    if tilt.position_known:
        errors.add("tilt", abs(tilt.position_fb - world.tilt_deg))
    if rotate.position_known:
        errors.add("rotate", _wrap(rotate.position_fb - world.rotate_deg))


@dataclass(frozen=True)
class Plan:
    daemons: int
    runs: int
    """Runs per daemon."""
    burners: int
    """CPU-bound neighbours of the busy condition."""
    full: bool = True
    """Each run calibrates the rotate and runs a session too (a smoke run only the tilt)."""


def one_run(r: Rider, rng: random.Random, errors: Errors, full: bool) -> None:
    """Place, calibrate both axes, home, a short session; each measured against the truth."""
    r.sim("place", tilt_deg=rng.uniform(-10.0, 60.0), rotate_deg=rng.uniform(0.0, 360.0))
    status = r.wait_for(ENDED, STEP_TIMEOUT_S, after=r.calibrate_tilt().timecode)
    if errors.ended("CalibrateTilt", status):
        tilt = r.calibration().tilt
        zero = r.sim("world").tilt_zero_counts
        if tilt is not None and zero is not None:
            errors.add("offset", abs(tilt.offset_counts - zero) / tilt.gain_counts_per_deg)
    if full:
        status = r.wait_for(ENDED, STEP_TIMEOUT_S, after=r.calibrate_rotate().timecode)
        errors.ended("CalibrateRotate", status)
    status = r.wait_for(ENDED, STEP_TIMEOUT_S, after=r.home().timecode)
    if not errors.ended("Home", status):
        return
    _positions(r, errors)
    if full:
        session(r, rng, errors)


def session(r: Rider, rng: random.Random, errors: Errors) -> None:
    """The tilt to a random angle and one revolution, then the positions against the truth."""
    steps: list[TiltStep | RotateStep] = [
        TiltStep(degrees=round(rng.uniform(10.0, 60.0), 1)),
        RotateStep(),
    ]
    try:
        reply = r.start(Session(name="bench", steps=steps))
    except CommandRefused as exc:  # the rotate calibration was refused: not calibrated
        with errors.lock:
            errors.outcomes[f"Start {exc.error.code}"] += 1
        return
    if errors.ended("Start", r.wait_for(ENDED, STEP_TIMEOUT_S, after=reply.timecode)):
        _positions(r, errors)


def one_daemon(tmp: Path, index: int, plan: Plan, seed: int, errors: Errors) -> None:
    """A daemon of its own and its runs (on a thread: a failure is kept for the caller).
    Each in a directory of its own: `start_daemon` writes its Zenoh config there."""
    config = tmp / "machine-homing.toml"
    home = tmp / f"h{index}"
    home.mkdir()
    try:
        daemon = start_daemon(home, f"h{index}", extra=["--config", str(config)])
        with errors.lock:
            errors.daemons.append(daemon)
        try:
            # Unsupervised: ten Riders in one busy process may miss heartbeats, and a paused
            # ride is not what this measures.
            with daemon.rider(timeout=10.0, supervise=False) as r:
                rng = random.Random(seed)
                for _ in range(plan.runs):
                    if errors.stop.is_set():
                        break
                    try:
                        one_run(r, rng, errors, plan.full)
                    except (MachineTimeout, CommandRefused) as exc:
                        with errors.lock:
                            errors.outcomes[f"run {type(exc).__name__}"] += 1
                        r.stop()  # any state: the next run starts from DONE
        finally:
            daemon.stop()
    except Exception as exc:  # noqa: BLE001 - re-raised on the main thread by `condition`
        with errors.lock:
            errors.failures.append(exc)


def condition(plan: Plan, neighbours: int, seed: int) -> tuple[Errors, float]:
    """The plan's daemons side by side, its runs each, beside `neighbours` CPU-bound processes."""
    errors = Errors()
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bench-homing-") as name:
        tmp = Path(name)
        (tmp / "machine-homing.toml").write_text(CONFIG)
        with burners(neighbours, tmp, plan.runs * 120.0 + 300.0):
            threads = [
                threading.Thread(
                    target=one_daemon, args=(tmp, i, plan, seed + i, errors), name=f"h{i}"
                )
                for i in range(plan.daemons)
            ]
            for t in threads:
                t.start()
            try:
                for t in threads:
                    t.join()
            except BaseException:  # interrupted: stop every daemon, so each run's wait ends
                errors.stop.set()
                with errors.lock:
                    started = list(errors.daemons)
                for daemon in started:
                    daemon.stop()
                for t in threads:
                    t.join(timeout=30.0)
                raise
    if errors.failures:
        raise errors.failures[0]
    return errors, time.monotonic() - t0


def _cells(values: list[float]) -> list[str]:
    d = Dist.of(values)
    return [str(d.n), f"{d.p50:.3f}", f"{d.p99:.3f}", f"{d.max:.3f}"]


def run(opts: Options) -> Section:
    # The smoke run: one tilt calibration and Home each way, no neighbour (it runs beside
    # every other benchmark's smoke run in the tests).
    plan = opts.pick(Plan(1, 1, 0, full=False), Plan(10, 5, 2), Plan(10, 20, 2))
    section = Section("homing", "15. Homing and calibration on a busy host")
    quiet, quiet_s = condition(plan, 0, seed=37)
    busy, busy_s = condition(plan, plan.burners, seed=37)
    busy_host = f"{plan.burners} CPU-bound neighbours"
    table = Table(
        "Reported minus true position (degrees): tilt offset after CalibrateTilt; tilt and"
        " rotate after each Home and each session",
        ["host", "what", "n", "p50", "p99", "worst"],
    )
    for host, errors in (("quiet", quiet), (busy_host, busy)):
        table.add(host, "tilt offset", *_cells(errors.offset))
        table.add(host, "tilt position", *_cells(errors.tilt))
        table.add(host, "rotate position", *_cells(errors.rotate))
    section.tables.append(table)
    outcomes = Table("How each measurement ended", ["host", "command", "ended", "count"])
    for host, errors in (("quiet", quiet), (busy_host, busy)):
        for key, count in sorted(errors.outcomes.items()):
            command, ended = key.split(" ", 1)
            outcomes.add(host, command, ended, count)
    section.tables.append(outcomes)
    for host, errors in (("quiet", quiet), ("busy", busy)):
        section.targets.append(
            Target.at_most(
                f"worst tilt offset ({host})",
                Dist.of(errors.offset).max,
                OFFSET_TOL_DEG,
                lambda v: f"{v:.3f}°",
            )
        )
        worst = max(Dist.of(errors.tilt).max, Dist.of(errors.rotate).max)
        section.targets.append(
            Target.at_most(
                f"worst position after Home or a session ({host})",
                worst,
                POSITION_TOL_DEG,
                lambda v: f"{v:.3f}°",
            )
        )
    section.notes.append(
        f"{plan.daemons} daemons side by side, {plan.runs} runs each ("
        + (
            "place, CalibrateTilt, CalibrateRotate, Home, a session of a tilt and one revolution"
            if plan.full
            else "a smoke run: place, CalibrateTilt, Home"
        )
        + f"): {quiet_s:.0f} s"
        f" quiet, {busy_s:.0f} s busy. Positions are the axis records' (unrounded), read at"
        " rest; the truth is `sim/world`. Refused measurements (a fault code above) are not"
        " errors: the machine said it could not measure, and did not report DONE."
    )
    return section


if __name__ == "__main__":
    sys.exit(main_for("bench.homing", __doc__ or "", run))
