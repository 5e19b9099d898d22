"""The loop watchdog: a scan thread that stops cycling is caught, and a danger is stopped.

A stall is a scan that has not completed a cycle for the watchdog limit. What it means depends
on the outputs, as a PLC runtime's watchdog "sensitivity" does: a stall while every output is
off could move nothing, so it is counted, logged and shown on `diag/cycle` and changes no
state; a stall while any output is energised is a danger, and the outputs go safe at once.

Two eyes see a stall. A thread watches the runner's heartbeat and, with an output energised,
latches the HAL safe (`GuardedHal`): outputs drop at once, and every later write is forced safe
too, so a loop that wakes up again cannot re-energise a relay with stale decisions. The scan
thread itself measures the gap since its last cycle when it runs again (`after_stall`), so a
stall the thread could not see (it was frozen too: SIGSTOP, a GIL held) becomes `FAULT_HW`
(`WATCHDOG`) in the first cycle after it, before any controller judges the lost time as motion.
The scan thread clears the latch only after it has put the machine into `FAULT_HW`. What
neither can catch, a process frozen as a whole, the supervisor's output guard catches from
outside (`service.core.scan.beat`, `service.supervision.outputguard`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from ride_machine.hal.base import Hal, Inputs, Outputs
from ride_machine.service.threads import TimedThread

from .beat import BeatWriter

log = logging.getLogger(__name__)


ARM_AFTER_CYCLES = 10
"""The first cycles do one-off work (first publications, caches); the watchdog starts after."""


class Pulse:
    """The scan's sign of life: the runner writes it after every cycle, the watchdog's thread
    reads it. Each field is one store, read whole: no lock between the two threads."""

    __slots__ = ("at", "count", "finished")

    def __init__(self) -> None:
        self.count = 0
        """Cycles completed."""
        self.at = 0.0
        """The clock time the latest cycle ended (set just before `count` moves)."""
        self.finished = False
        """True once the loop has left its cycle for good (a stop, a failure): beats end on
        purpose, the outputs go safe on the loop's own way out, and the watchdog stands down
        (a slow teardown is no stall)."""


class GuardedHal:
    """A `Hal` whose outputs a watchdog can latch safe from another thread, and that knows
    whether the outputs it last wrote energise anything."""

    def __init__(self, inner: Hal, beat: BeatWriter | None = None) -> None:
        self.inner = inner
        self.scan_inputs: Callable[[], Inputs] = inner.scan_inputs
        """The inner HAL's own: the latch guards outputs only (no wrapper call per cycle)."""
        self.latched = False
        """Set by the watchdog's thread, cleared by the scan thread (one bool: atomic), read
        every cycle; a plain attribute, where an `Event` costs a Python call per read."""
        self.energised = False
        """Any output on in the latest write: set before a write that energises, cleared
        after one that does not, so a thread that reads it never sees False while a relay
        may be on."""
        self.stalled_s: float | None = None
        """How long the scan had stalled when the watchdog latched (None: not said, as when
        the supervisor's guard latched from its own process)."""
        self._beat = beat.rec if beat is not None else None
        """The record the supervisor may latch from its own process (`service.core.scan.beat`)."""

    def latch_safe(self, stalled_s: float | None = None) -> None:
        """Outputs safe now and at every later write, until the scan thread `unlatch`es;
        `stalled_s`: how long the scan had stalled (the machine's fault says so)."""
        self.stalled_s = stalled_s
        self.latched = True
        self.inner.force_all_outputs_safe()
        self.energised = False

    def unlatch(self) -> None:
        self.latched = False
        if self._beat is not None:
            self._beat.latched = 0

    def scan_outputs(self, outputs: Outputs) -> None:
        beat = self._beat
        if beat is not None and beat.latched and not self.latched:
            # The supervisor forced the outputs safe over a stall (the scan's own gap check
            # has normally tripped already): latch here too, so the loop takes the fault.
            self.latched = True
        if self.latched:
            self.inner.force_all_outputs_safe()
            self.energised = False
            return
        on = any(outputs.ro.values())
        if on:
            self.energised = True
        self.inner.scan_outputs(outputs)
        if not on:
            self.energised = False

    def force_all_outputs_safe(self) -> None:
        self.inner.force_all_outputs_safe()
        self.energised = False

    def read_estop(self) -> bool:
        return self.inner.read_estop()

    def close(self) -> None:
        self.inner.close()


class Watchdog(TimedThread):
    """Trips when the scan's `pulse` has not moved for `limit_s` while an output is energised;
    with every output off it only says so. It checks a third of a limit after the latest
    beat would be `limit` old (one wake-up per limit on a healthy loop), then every third of
    a limit, so a stall is tripped when it has lasted between 1 and 4/3 limits.

    Made before the runner, which it is given to: the runner beats its `pulse` and asks it to
    judge a stall the scan thread saw itself (`after_stall`)."""

    def __init__(
        self,
        hal: GuardedHal,
        limit_s: float,
        *,
        on_trip: Callable[[float], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """`limit_s`: the config's `loop.watchdog_limit_s`, the one place it is worked out."""
        super().__init__("watchdog")
        self.pulse = Pulse()
        self.hal = hal
        self.limit = limit_s
        self.period = limit_s / 3
        self.on_trip = on_trip
        self.clock = clock
        self.trips = 0
        self.tripped_at: float | None = None
        self._said = False
        """The stall under way (outputs off) was logged by the thread."""

    def _run(self) -> None:
        # Armed once the first cycles have completed: before them the outputs are safe
        # anyway, and start-up work (imports, gc.freeze) must not count as a stall.
        pulse = self.pulse
        last_beat = pulse.count
        last_change = self.clock()
        armed = False
        wait = self.period
        # A wake-up per limit, ~25 a second at 10 ms: `TimedThread.sleep` (bench.cost).
        while self.sleep(wait):
            wait = self.period
            if pulse.finished:
                return
            beat = pulse.count
            now = self.clock()
            if not armed:
                armed = beat >= ARM_AFTER_CYCLES
            if beat != last_beat:
                last_beat = beat
                self._said = False
                last_change = pulse.at
                if armed and self.tripped_at is None:
                    wait = self.next_check(last_change, now)
                if self.tripped_at is not None and not self.hal.latched:
                    self.tripped_at = None  # the loop recovered and took the fault
                continue
            if armed and self.tripped_at is None and now - last_change > self.limit:
                self._stalled(now, now - last_change)

    def _stalled(self, now: float, stalled_s: float) -> None:
        """Seen from the watchdog's thread: a danger trips; a stall with every output off is
        said once (the scan thread counts it, with its length, when it runs again)."""
        if self.hal.energised:
            self.check(now, stalled_s)
        elif not self._said:
            self._said = True
            log.warning(
                "event=loop_stalled stalled_s=%.4f limit_s=%.4f outputs=off action=none",
                stalled_s,
                self.limit,
            )

    def after_stall(self, now: float, stalled_s: float) -> bool:
        """Seen from the scan thread as it runs again after `stalled_s` without a cycle (more
        than the limit): an energised output trips now, in this cycle, if the thread has not
        (True: the loop takes `FAULT_HW`); a stall with every output off is logged (False)."""
        self._said = False
        if self.hal.latched:
            return True
        if self.hal.energised:
            self.check(now, stalled_s)
            return True
        log.warning(
            "event=stall stalled_s=%.4f limit_s=%.4f outputs=off action=none",
            stalled_s,
            self.limit,
        )
        return False

    def next_check(self, beat_at: float, now: float) -> float:
        """Seconds to sleep after a beat at `beat_at`: nothing can trip before it is `limit`
        old; checking a plain interval later keeps the old 1–4/3 limits bound (a stall of just
        over one limit that ends by itself is not tripped, as before)."""
        return max(self.period, beat_at + self.limit + self.period - now)

    def check(self, now: float, stalled_s: float) -> None:
        """Trip: latch outputs safe and report (also callable directly, e.g. from tests)."""
        self.hal.latch_safe(stalled_s)
        self.trips += 1
        self.tripped_at = now
        log.error("event=watchdog_trip stalled_s=%.4f limit_s=%.4f", stalled_s, self.limit)
        if self.on_trip is not None:
            self.on_trip(stalled_s)
