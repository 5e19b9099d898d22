"""E-stop reaction: cycles from the cycle that first sees the input to safe outputs.

In-process: the machine on the fake-clock rig runs the default session; the E-stop is pressed
at a random phase between two cycles, after a random number of cycles, thousands of times.
Then a smaller run against a real daemon process: the E-stop is injected through the
simulator's `sim/estop` queryable at a random phase, and the cycle of the E-stop input's IO
publication is compared with that of the relays' switching off (both stamped with their
cycle's start).
"""

from __future__ import annotations

import contextlib
import random
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh

from bench.common import Dist, Options, Section, Table, Target, main_for, ms, share
from bench.daemon import HomingFailed, bench_daemon, home_and_start
from ride_machine.rider.client import CommandRefused, Rider
from ride_machine.schema.codec import DecodeError, Format, decode
from ride_machine.schema.commands import Command
from ride_machine.schema.io import IoKind, IoValue
from ride_machine.schema.status import MOTION_STATES, MachineState
from tests.rig import Rig, known_calibration

PERIOD_S = 0.010
MAX_REACTION_CYCLES = 10
"""A reaction slower than this is recorded as a failure rather than waited for."""


RESTART = {
    MachineState.IDLE: Command.START,
    MachineState.DONE: Command.HOME,
    MachineState.WARNING_NOT_HOME: Command.HOME,
}
"""Keeps the rig moving: a finished session leaves the tilt off home, so home, then start."""


@dataclass
class Reactions:
    """How many cycles each injection took to reach safe outputs, with its context."""

    cycles: Counter[int] = field(default_factory=Counter)
    relays_on_before: int = 0
    states_before: Counter[str] = field(default_factory=Counter)
    delay_s: list[float] = field(default_factory=list)
    """Input change → safe outputs written, in seconds (phase wait + the cycle's own work)."""

    @property
    def n(self) -> int:
        return sum(self.cycles.values())


def in_process(n: int, seed: int = 8) -> Reactions:
    """`n` injections on the fake-clock rig, at random phases, mostly while relays are on."""
    rng = random.Random(seed)
    rig = Rig(calibration=known_calibration())
    rig.home()
    assert rig.send(Command.START).success
    period = rig.period
    out = Reactions()
    for _ in range(n):
        for _ in range(rng.randint(1, 40)):
            rig.step()
            next_command = RESTART.get(rig.state)
            if next_command is not None:
                rig.send(next_command)
        out.states_before[rig.state.value] += 1
        out.relays_on_before += rig.relays_on()
        phase = rng.random()
        rig.clock.advance(phase * period)
        rig.hal.press_estop()
        rig.clock.advance((1.0 - phase) * period)
        t0 = time.perf_counter()
        rig.loop.step(rig.clock())
        work = time.perf_counter() - t0
        cycles = 0
        while rig.relays_on() or rig.state is not MachineState.FAULT_ESTOP:
            cycles += 1
            if cycles > MAX_REACTION_CYCLES:
                break
            rig.step()
        out.cycles[cycles] += 1
        out.delay_s.append((1.0 - phase) * period + work)
        rig.hal.release_estop()
        rig.step()
        rig.send(Command.RESUME)
    return out


@dataclass
class Observed:
    """IO publications and statuses a Rider received, in arrival order."""

    io: list[IoValue] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    changed: threading.Event = field(default_factory=threading.Event)

    def on_io(self, sample: zenoh.Sample) -> None:
        try:
            point = decode(IoValue, sample.payload.to_bytes(), Format.MSGPACK)
        except DecodeError:
            return
        assert isinstance(point, IoValue)
        with self.lock:
            self.io.append(point)
        self.changed.set()

    def since(self, index: int) -> list[IoValue]:
        with self.lock:
            return self.io[index:]

    def relays(self) -> dict[str, bool]:
        """The latest published value of every relay output."""
        with self.lock:
            return {p.name: bool(p.value) for p in self.io if p.kind is IoKind.RO}

    def wait(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Poll `pred` whenever a publication arrives (and every 50 ms), up to `timeout`."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.changed.clear()
            if pred():
                return True
            self.changed.wait(0.05)
        return False


def _motion_relay_on(obs: Observed) -> bool:
    r = obs.relays()
    return bool(r.get("rotateRelay") or r.get("tiltRelay"))


def real_process(n: int, seed: int = 8) -> tuple[Reactions, int]:
    """`n` injections into a daemon process; returns the reactions and how many were unclear."""
    rng = random.Random(seed)
    out = Reactions()
    unclear = 0
    with contextlib.ExitStack() as stack:
        daemon = stack.enter_context(bench_daemon(PERIOD_S, calibrated=True))
        rider: Rider = stack.enter_context(daemon.rider(supervise=False))
        obs = Observed()
        sub = rider.session.declare_subscriber(f"{rider.base}/io/**", obs.on_io)
        stack.callback(sub.undeclare)
        try:
            home_and_start(rider)
        except HomingFailed:
            return out, n  # the host was too busy to home: nothing to inject into
        for _ in range(n):
            if not obs.wait(lambda: _motion_relay_on(obs), timeout=10.0):
                unclear += 1
                if rider.status().state not in MOTION_STATES:
                    try:
                        home_and_start(rider)
                    except HomingFailed:
                        return out, n - out.n
                continue
            out.relays_on_before += 1
            out.states_before[rider.status().state.value] += 1
            time.sleep(rng.uniform(0.0, PERIOD_S))
            mark = len(obs.since(0))
            rider.sim("estop", pressed=True)

            def reacted(mark: int = mark) -> bool:
                return _estop_and_off(obs.since(mark)) is not None

            safe = obs.wait(reacted, timeout=2.0)
            times = _estop_and_off(obs.since(mark))
            if not safe or times is None:
                unclear += 1
            else:
                t_input, t_off = times
                out.cycles[round((t_off - t_input) / PERIOD_S)] += 1
            rider.sim("estop", pressed=False)
            obs.wait(lambda: not rider.status().estop.active, timeout=2.0)
            with contextlib.suppress(CommandRefused):
                rider.resume()
    return out, unclear


def _estop_and_off(points: list[IoValue]) -> tuple[float, float] | None:
    """(stamp of the E-stop input's change, stamp of the last relay switching off)."""
    t_input = next((p.time for p in points if p.name == "estop"), None)
    offs = [p.time for p in points if p.kind is IoKind.RO and not p.value]
    if t_input is None or not offs:
        return None
    return t_input, max(offs)


def _row(table: Table, where: str, r: Reactions, extra: str) -> None:
    same = r.cycles.get(0, 0)
    spread = ", ".join(f"{k}: {v}" for k, v in sorted(r.cycles.items()))
    table.add(where, r.n, r.relays_on_before, f"{same} ({share(same, r.n)})", spread, extra)


def run(opts: Options) -> Section:
    n_rig = opts.pick(200, 10_000, 50_000)
    n_real = opts.pick(3, 100, 500)
    section = Section("estop", "3. E-stop reaction")
    t0 = time.perf_counter()
    rig = in_process(n_rig)
    rig_s = time.perf_counter() - t0
    real, unclear = real_process(n_real)
    table = Table(
        "Cycles from the first cycle that sees the E-stop to all relays off",
        ["where", "injections", "relays on before", "same cycle (0)", "cycles: count", "notes"],
    )
    delay = Dist.of(rig.delay_s)
    _row(
        table,
        f"fake-clock rig, {PERIOD_S * 1e3:g} ms",
        rig,
        f"{rig_s:.1f} s wall; states before: "
        + ", ".join(f"{k} {v}" for k, v in rig.states_before.most_common()),
    )
    _row(
        table,
        f"daemon process, {PERIOD_S * 1e3:g} ms, via sim/estop",
        real,
        f"{unclear} injections unclear (no relay on in time, or no publication seen)",
    )
    section.tables.append(table)
    timing = Table(
        "Input change → safe outputs written, in time (fake-clock rig, random phase)",
        ["p50 ms", "p99 ms", "max ms", "max of period"],
        note="the wait for the next cycle to sample the input, plus that cycle's work up to"
        " the output write",
    )
    timing.add(ms(delay.p50), ms(delay.p99), ms(delay.max), share(delay.max, PERIOD_S))
    section.tables.append(timing)
    for where, r in (("rig", rig), ("daemon process", real)):
        same = r.cycles.get(0, 0)
        section.targets.append(
            Target(
                f"E-stop handled in the same cycle ({where})",
                "100 %",
                share(same, r.n),
                same == r.n if r.n else None,
                f"{r.n - same} of {r.n} later" if r.n else "no injection measured",
            )
        )
    section.notes.append(
        "The process run injects through `sim/estop`, which the scan thread applies between"
        " cycles; the E-stop input's IO publication and the relays' off publications carry"
        " their cycle's start time, so equal stamps mean the same cycle."
    )
    return section


if __name__ == "__main__":
    sys.exit(main_for("bench.estop", __doc__ or "", run))
