"""The real-time runner: absolute deadlines, early wake for commands, timing statistics."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from ride_machine.schema.status import Fault, FaultCode

from .beat import BeatWriter
from .loop import ScanLoop
from .timing import CycleStats
from .watchdog import ARM_AFTER_CYCLES, Pulse, Watchdog

log = logging.getLogger(__name__)

MAX_CONSECUTIVE_ERRORS = 50
"""A loop that fails this many cycles in a row stops the daemon (a supervisor restarts it)."""

CLOCK_STEP_S = 0.01
"""A change of the host's wall clock against the steady clock larger than this is one the
machine's wall times follow (`RealtimeRunner`'s `wall`); NTP's slewing moves both clocks alike."""
CLOCK_SET_S = 0.1
"""A change larger than this, seen at once, is the clock being set (NTP steps from 128 ms): it is
logged and recorded (`clock_set`). Smaller ones are a drift, followed without a word: a host
whose wall clock runs apart from its steady clock (a virtual machine's, 5 ms a second on the
project's test host) would otherwise record a `clock_set` event every two seconds."""
WALL_READ_MAX_S = 0.001
"""Both clocks read within this, or the sample is left for the next cycle (the thread was
preempted between the reads, which would look like a step)."""


class LoopFailed(Exception):
    """The scan loop kept failing; outputs were made safe before this was raised."""


class RealtimeRunner:
    """Runs `ScanLoop.step` on absolute deadlines and records how well it kept them.

    Between deadlines it sleeps on the inbox's event, so a command is answered as soon as it
    arrives instead of at the next cycle; the last `spin_s` before a deadline is busy-waited.
    On an overrun it counts the missed cycles and skips to the next future deadline.
    """

    def __init__(
        self,
        loop: ScanLoop,
        period_s: float,
        stats: CycleStats,
        *,
        spin_s: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
        watchdog: Watchdog | None = None,
        beat: BeatWriter | None = None,
        wall: Callable[[], float] | None = None,
    ) -> None:
        """`watchdog`: the runner beats its pulse after every cycle, and a cycle that starts
        (or ends) longer than its limit after the previous one ended is a stall, which it
        judges (`Watchdog.after_stall`) before the cycle runs; None: no stall is judged.
        `beat`: the record a supervisor watches from its own process, stamped after every
        cycle. `wall`: the host's wall clock, compared with `clock` before every cycle: when it
        was set (NTP's first sync on a Revolution Pi, which has no battery clock; a resumed
        virtual machine) the loop's wall times follow it (`ScanLoop.set_wall_offset`), or every
        motion command's timecode would be judged against the clock the daemon started with."""
        self.loop = loop
        self.period = period_s
        self.stats = stats
        self.spin_s = spin_s
        self.clock = clock
        self.stop_event = threading.Event()
        self._stopping = False
        """`stop_event` as a plain bool, read every cycle (an `Event` read is a Python call)."""
        self.watchdog = watchdog
        self.pulse = Pulse() if watchdog is None else watchdog.pulse
        """Beaten after every completed cycle (the watchdog's thread reads it): its `count`
        of cycles, the clock time the latest ended (`at`), `finished` once they have ended."""
        self.pulse.at = clock()
        self.errors = 0
        self.beat = beat
        self.wall = wall

    def stop(self) -> None:
        self._stopping = True
        self.stop_event.set()
        self.loop.inbox.wake.set()

    def run(self) -> None:
        """Cycle until `stop()`; outputs are forced safe on every way out."""
        try:
            self._run()
        finally:
            self.pulse.finished = True  # no cycle runs any more: nothing for the watchdog to watch
            self.loop.go_safe()
            if self.beat is not None:
                self.beat.finish()

    def _run(self) -> None:
        clock, period = self.clock, self.period
        loop, stats = self.loop, self.stats
        lock, pulse = loop.lock, self.pulse
        limit = self.watchdog.limit if self.watchdog is not None else float("inf")
        shared = self.beat.rec if self.beat is not None else None
        guard = loop.guard
        wall = self.wall
        deadline = clock()  # first scan at once: commands need a real input image
        consecutive = 0
        while self._sleep_until(deadline):
            with lock:
                start = clock()
                if wall is not None:
                    self._follow_wall(wall, start)
                if start - pulse.at > limit:  # stopped between cycles
                    self._stalled(start, start - pulse.at)
                try:
                    loop.step(start)
                    consecutive = 0
                except Exception as exc:  # noqa: BLE001 - any failure must end in safe outputs
                    consecutive += 1
                    self._on_error(exc, start, consecutive)
                end = clock()
                if end - start > limit:  # stopped inside this cycle: safe before the next
                    self._stalled(end, end - start)
            jitter = start - deadline
            deadline += period
            missed = 0
            if end > deadline:
                missed = int((end - deadline) // period) + 1
                deadline += missed * period
            stats.record(jitter, end - start, missed)
            stats.commands = loop.commands_handled
            pulse.at = end
            pulse.count = beats = pulse.count + 1
            if shared is not None:
                shared.cycles = beats  # the supervised world waits on scans (sim/world)
                if guard is not None:  # what the relays did, for a stall found with them off
                    shared.energised = guard.energised
                shared.beat_ns = int(end * 1e9)  # one store: what the supervisor watches

    def _follow_wall(self, wall: Callable[[], float], now: float) -> None:
        clock = self.clock
        before = clock()
        at = wall()
        after = clock()
        if after - before > WALL_READ_MAX_S:
            return
        offset = at - (before + after) / 2
        step = abs(offset - self.loop.wall_offset)
        if step > CLOCK_STEP_S:
            self.loop.set_wall_offset(offset, now, record=step > CLOCK_SET_S)

    def _sleep_until(self, deadline: float) -> bool:
        """Wait for the deadline on the inbox's event, serving commands as they come; the
        last `spin_s` busy-waited. False once stopped."""
        clock, spin, loop = self.clock, self.spin_s, self.loop
        wake = loop.inbox.wake
        while not self._stopping:
            remaining = deadline - clock()
            if remaining <= spin:
                while spin and clock() < deadline:
                    pass
                return not self._stopping
            if wake.wait(remaining - spin):
                if self._stopping:
                    return False
                with loop.lock:
                    loop.service_inbox(clock())
        return False

    def _stalled(self, now: float, stalled_s: float) -> None:
        """No cycle for longer than the limit (the process was stopped, starved or blocked):
        the watchdog judges it before this cycle runs; it is counted either way. The first
        cycles (start-up work) are not judged."""
        if self.pulse.count < ARM_AFTER_CYCLES:
            return
        tripped = self.watchdog.after_stall(now, stalled_s) if self.watchdog is not None else False
        self.stats.stall(stalled_s, tripped)

    def _on_error(self, exc: Exception, now: float, consecutive: int) -> None:
        self.errors += 1
        try:
            self.loop.go_safe()
        finally:
            if consecutive == 1:
                log.error("event=loop_exception error=%r", exc, exc_info=exc)
                self.loop.state_machine.external_fault(
                    Fault(code=FaultCode.LOOP_EXCEPTION, message=f"scan loop failed: {exc!r}"),
                    now,
                )
        if consecutive >= MAX_CONSECUTIVE_ERRORS:
            raise LoopFailed(f"scan loop failed {consecutive} cycles in a row: {exc!r}") from exc
