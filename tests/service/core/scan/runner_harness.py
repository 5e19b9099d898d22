"""A rig run by a real `RealtimeRunner` on simulated time (tests/service/core/scan/test_runner.py,
test_wall_clock.py): deadlines on a ticking fake clock, wake-ups and arrivals scripted."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.status import MachineState
from ride_machine.service.core.scan.beat import BeatWriter
from ride_machine.service.core.scan.runner import RealtimeRunner
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.scan.watchdog import Watchdog
from tests.rig import FakeClock, Rig, known_calibration

S = MachineState
PERIOD = 0.010
TICK = 1e-6


class TickingClock(FakeClock):
    """Simulated time that moves on by `tick` at every read, so a busy-wait makes progress."""

    def __init__(self, tick: float = TICK) -> None:
        super().__init__()
        self.tick = tick
        self.reads = 0

    def __call__(self) -> float:
        self.reads += 1
        if self.reads > 10_000_000:
            raise AssertionError("runner is spinning without end")
        self.t += self.tick
        return self.t


class FakeWake:
    """The inbox's wake event on simulated time: a wait moves the clock instead of sleeping.

    `oversleep` makes every timed-out wait return that much late, as a loaded OS does;
    `arrivals` are (time, action) pairs run when the wait reaches them (a command arriving).
    """

    def __init__(self, clock: TickingClock, oversleep: float = 0.0) -> None:
        self.clock = clock
        self.oversleep = oversleep
        self.arrivals: list[tuple[float, Callable[[], None]]] = []
        self.waits: list[float] = []
        self.flag = False

    def set(self) -> None:
        self.flag = True

    def clear(self) -> None:
        self.flag = False

    def is_set(self) -> bool:
        return self.flag

    def wait(self, timeout: float | None = None) -> bool:
        assert timeout is not None, "the runner must always wait with a deadline"
        assert timeout > 0
        self.waits.append(timeout)
        if len(self.waits) > 1_000_000:
            raise AssertionError("runner keeps waking without progress")
        if self.flag:
            return True
        until = self.clock.t + timeout
        if self.arrivals and self.arrivals[0][0] <= until:
            at, action = self.arrivals.pop(0)
            self.clock.t = max(self.clock.t, at)
            action()
            return self.flag
        self.clock.t = until + self.oversleep
        return False


class Harness:
    """A rig whose loop is run by a `RealtimeRunner` on simulated time, step by step observed."""

    def __init__(  # noqa: PLR0913 - the cycle count, then keyword-only scenario knobs
        self,
        cycles: int,
        *,
        cost: Callable[[int], float] = lambda i: 0.002,
        fail: Callable[[int], bool] = lambda i: False,
        fail_after_step: bool = False,
        homed: bool = False,
        running: bool = False,
        spin_s: float = 0.0,
        oversleep: float = 0.0,
        stall_limit: float | None = None,
        estopped: bool = False,
        beat: BeatWriter | None = None,
        wall: Callable[[], float] | None = None,
    ) -> None:
        """`stall_limit`: the watchdog limit, with the watchdog's latch between the loop and
        the HAL and its `after_stall` judging the runner's stalls (as the daemon wires it)."""
        self.clock = TickingClock()
        guarded = stall_limit is not None
        self.rig = Rig(calibration=known_calibration(), clock=self.clock, guarded=guarded)
        self._arrange(homed=homed, running=running, estopped=estopped)
        loop = self.rig.loop
        self.wake = FakeWake(self.clock, oversleep)
        loop.inbox.wake = self.wake  # type: ignore[assignment]
        self.stats = CycleStats(PERIOD, window=100, now=self.clock())
        self.watchdog: Watchdog | None = None
        if self.rig.guard is not None and stall_limit is not None:
            self.watchdog = Watchdog(self.rig.guard, stall_limit)
        self.runner = RealtimeRunner(
            loop,
            PERIOD,
            self.stats,
            spin_s=spin_s,
            clock=self.clock,
            watchdog=self.watchdog,
            beat=beat,
            wall=wall,
        )
        self.starts: list[float] = []
        self.ends: list[float] = []
        self.seen: list[tuple[MachineState, bool]] = []
        """(state, any relay on) at the start of each cycle: what the previous cycle left."""
        self._observe(cycles, cost, fail, fail_after_step)
        self.t0 = self.clock.t

    def _arrange(self, *, homed: bool, running: bool, estopped: bool) -> None:
        """The rig to the scenario's start: homed, mid-session, or after an E-stop let go."""
        if homed or running:
            self.rig.home()
        if running:
            assert self.rig.send(Command.START).success
            self.rig.run_until(self.rig.relays_on)
        if estopped:
            self.rig.hal.press_estop()
            self.rig.step(3)
            self.rig.hal.release_estop()
            self.rig.step(3)

    def _observe(
        self,
        cycles: int,
        cost: Callable[[int], float],
        fail: Callable[[int], bool],
        fail_after_step: bool,
    ) -> None:
        """Wrap the loop's step: record each cycle's start and end, advance the clock by its
        cost, inject its failure, and stop the runner after `cycles`."""
        loop = self.rig.loop
        real_step = loop.step

        def step(now: float) -> None:
            i = len(self.starts)
            self.starts.append(now)
            self.seen.append((self.rig.state, self.rig.relays_on()))
            try:
                if fail(i) and not fail_after_step:
                    raise RuntimeError(f"injected failure in cycle {i}")
                real_step(now)
                self.clock.advance(cost(i))
                if fail(i):
                    raise RuntimeError(f"injected failure after cycle {i} wrote its outputs")
            finally:
                self.ends.append(self.clock.t)
                if len(self.starts) >= cycles:
                    self.runner.stop()

        loop.step = step  # type: ignore[method-assign]

    def run(self) -> None:
        self.runner.run()

    def grid_offsets(self) -> list[float]:
        """Each cycle's start relative to its ideal slot on the first cycle's grid, in periods."""
        first = self.starts[0]
        return [(s - first) / PERIOD for s in self.starts]


def assert_on_grid(h: Harness) -> None:
    for k, offset in enumerate(h.grid_offsets()):
        assert offset == pytest.approx(round(offset), abs=50 * TICK / PERIOD), (k, offset)
