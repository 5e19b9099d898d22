"""A Rider process that loads the daemon: paced commands while watching every key, or rate steps.

`paced`: `--rate` sequential commands per second on an absolute schedule for `--duration`
seconds, with a watcher decoding every status / IO / axis / diag publication (and restarting
the session whenever it ends, so the axes keep moving). `steps`: open-loop command rates, each
for `--step-s`, with the daemon's diag reset before and read after every step.
Both print `ready` once loaded and `result <json>` at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import zenoh

from bench.common import CpuMeter, Dist
from bench.daemon import HomingFailed, home_and_start
from ride_machine.rider.client import Rider, RiderError
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.status import MachineState, Status

STEP_TIMEOUT_S = 2.0
RESTART = frozenset(
    {MachineState.IDLE, MachineState.DONE, MachineState.WARNING_NOT_HOME, MachineState.FAULT_HW}
)
"""States in which the paced load sets the machine moving again (home, or start when IDLE)."""
MAX_IN_FLIGHT = 256


@dataclass
class Watch:
    """Counts every publication and keeps what the cross-checks need."""

    samples: dict[str, int] = field(default_factory=dict)
    axis_times: dict[str, list[tuple[int, float]]] = field(default_factory=dict)
    state: MachineState | None = None
    fault: str | None = None
    stop: threading.Event = field(default_factory=threading.Event)

    def run(self, rider: Rider) -> None:
        keys = ("status", "io/**", "axis/**", "diag/**")
        while not self.stop.is_set():
            for update in rider.watch(keys, timeout=0.5):
                kind = type(update).__name__
                self.samples[kind] = self.samples.get(kind, 0) + 1
                if isinstance(update, Status):
                    self.state = update.state
                    self.fault = str(update.fault.code) if update.fault else None
                elif isinstance(update, AxisRecord):
                    self.axis_times.setdefault(update.axis, []).append((update.cycle, update.time))
                if self.stop.is_set():
                    return


def axis_jitter(times: list[tuple[int, float]], period: float) -> Dist:
    """Wake-up lateness seen from outside: each record's stamp against the cycle grid.

    A record's time is its cycle's start, so `time - cycle * period` is its deadline's offset
    plus its lateness. After an overrun the runner skips whole deadlines, which only raises the
    offset, never lowers it: the lowest offset from each record on is that record's baseline,
    and the lateness is its height above it.
    """
    if len(times) < 2:
        return Dist.of([])
    offsets = [t - c * period for c, t in times]
    lateness = []
    floor = float("inf")
    for offset in reversed(offsets):
        floor = min(floor, offset)
        lateness.append(offset - floor)
    return Dist.of(lateness)


def paced(
    rider: Rider, rate: float, duration: float, motion: bool, period: float
) -> dict[str, Any]:
    faults: list[str] = []
    if motion:
        try:
            faults = home_and_start(rider)
        except HomingFailed as exc:
            faults, motion = [*exc.faults, "homing abandoned"], False
    watch = Watch()
    watcher = threading.Thread(target=watch.run, args=(rider,), name="watch", daemon=True)
    watcher.start()
    rtts: list[float] = []
    errors = restarts = late = 0
    print("ready", flush=True)
    t0 = time.monotonic()
    n = int(rate * duration)
    for i in range(n):
        due = t0 + i / rate
        wait = due - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        else:
            late += 1
        start = time.perf_counter()
        try:
            state = watch.state
            if motion and state in RESTART:
                watch.state = None  # act once per status, not once per command
                if state is MachineState.FAULT_HW:
                    faults.append(watch.fault or "FAULT_HW")
                if state is MachineState.IDLE:
                    rider.start()
                    restarts += 1
                else:
                    rider.home()
            else:
                rider.check_home()
        except RiderError:
            errors += 1
        rtts.append(time.perf_counter() - start)
    elapsed = time.monotonic() - t0
    watch.stop.set()
    watcher.join(timeout=2.0)
    jitter = {a: axis_jitter(t, period).__dict__ for a, t in watch.axis_times.items()}
    return {
        "sent": n,
        "errors": errors,
        "late": late,
        "restarts": restarts,
        "faults": faults,
        "rate": n / elapsed,
        "rtt": Dist.of(rtts).__dict__,
        "samples": watch.samples,
        "axis_jitter": jitter,
    }


@dataclass
class StepCounts:
    ok: int = 0
    failed: int = 0
    done: int = 0
    rtts: list[float] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)


def one_step(
    rider: Rider, rate: float, seconds: float, daemon_pid: int | None, tag: str
) -> dict[str, Any]:
    """Open-loop `check/home` at `rate`/s for `seconds`; every reply is checked for success."""
    session, key = rider.session, f"{rider.base}/cmd/check/home"
    counts = StepCounts()
    in_flight = threading.BoundedSemaphore(MAX_IN_FLIGHT)
    rider.diag(reset=True)
    cpu = CpuMeter(daemon_pid, family=True) if daemon_pid else None
    if cpu:
        cpu.start()
    own = CpuMeter(os.getpid())
    own.start()

    def handler(sent: float) -> zenoh.handlers.Callback[zenoh.Reply]:
        def on_reply(reply: zenoh.Reply) -> None:
            rtt = time.perf_counter() - sent
            ok = reply.ok is not None and msgpack.unpackb(reply.ok.payload.to_bytes())["success"]
            with counts.lock:
                counts.rtts.append(rtt)
                if ok:
                    counts.ok += 1
                else:
                    counts.failed += 1

        def on_done() -> None:
            with counts.lock:
                counts.done += 1
            in_flight.release()

        return zenoh.handlers.Callback(on_reply, on_done)

    n = max(1, int(rate * seconds))
    stalled = 0
    t0 = time.monotonic()
    for i in range(n):
        wait = t0 + i / rate - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        if not in_flight.acquire(timeout=STEP_TIMEOUT_S):
            stalled += 1
            break
        payload = msgpack.packb({"transaction_id": f"{tag}-{rate:g}-{i}"})
        session.get(
            key,
            handler(time.perf_counter()),
            payload=payload,
            encoding="application/msgpack",
            timeout=STEP_TIMEOUT_S,
        )
    send_s = time.monotonic() - t0
    drain = time.monotonic() + 2 * STEP_TIMEOUT_S
    while counts.done < n - stalled and time.monotonic() < drain:
        time.sleep(0.01)
    cpu_pct = cpu.percent() if cpu else float("nan")
    own_pct = own.percent()
    diag = rider.diag()
    with counts.lock:
        rtt = Dist.of(counts.rtts)
        return {
            "target": rate,
            "sent": n - stalled,
            "achieved": (n - stalled) / send_s,
            "ok": counts.ok,
            "failed": counts.failed,
            "unanswered": n - stalled - counts.ok - counts.failed,
            "rtt": rtt.__dict__,
            "overruns": diag.overruns,
            "missed": diag.missed_cycles,
            "exec_p99": diag.execution.p99,
            "exec_max": diag.execution.max,
            "jitter_p99": diag.jitter.p99,
            "cpu": cpu_pct,
            "generator_cpu": own_pct,
        }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("mode", choices=["paced", "steps"])
    parser.add_argument("--connect", required=True)
    parser.add_argument("--zenoh-config", type=Path, required=True)
    parser.add_argument("--period", type=float, default=0.010, help="the daemon's period")
    parser.add_argument("--rate", type=float, default=200.0, help="paced: commands per second")
    parser.add_argument("--duration", type=float, default=10.0, help="paced: seconds")
    parser.add_argument("--motion", action="store_true", help="paced: home, run sessions")
    parser.add_argument("--rates", default="500,1000", help="steps: comma-separated rates")
    parser.add_argument("--step-s", type=float, default=3.0, help="steps: seconds per rate")
    parser.add_argument("--daemon-pid", type=int, help="steps: measure this process's CPU")
    args = parser.parse_args(argv)
    with Rider(
        "m1", connect=[args.connect], zenoh_config_path=args.zenoh_config, supervise=False
    ) as rider:
        if args.mode == "paced":
            result = paced(rider, args.rate, args.duration, args.motion, args.period)
        else:
            print("ready", flush=True)
            steps = []
            for rate in (float(r) for r in args.rates.split(",")):
                step = one_step(rider, rate, args.step_s, args.daemon_pid, rider.rider_id[:8])
                steps.append(step)
                print("step " + json.dumps(step), flush=True)
            result = {"steps": steps}
    print("result " + json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
