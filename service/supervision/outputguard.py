"""The supervisor's output guard: outputs safe when the daemon's scan stops, from outside it.

The daemon stamps a shared record after every cycle (`service.core.scan.beat`). A thread here reads
the stamp and sleeps until it would be `limit` old; if it has not moved by then, the scan has
stopped. If any of the ride's relays is on in the process image at that moment, the guard
latches the record (the daemon, should it wake, writes nothing but the safe state until it has
taken `FAULT_HW`) and writes the safe image through the supervisor's own handle — in the
supervisor's process, which does not freeze with the daemon. A stall with every relay off
could move nothing: it is only reported. A scan that stays stopped past `hang_s` is a hung
daemon, whatever its outputs: the supervisor kills and restarts it.

One wake-up per limit while the daemon is healthy; a stall is acted on within a few hundred
microseconds of reaching the limit (plus this thread's wake-up on a busy host).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from ride_machine.service.core.scan.beat import Beat, BeatReader
from ride_machine.service.core.scan.tuning import SCHED_SLICE_NS, set_sched_slice
from ride_machine.service.threads import TimedThread

log = logging.getLogger("machine.supervisor")

MARGIN_S = 0.0005
"""Looked at this long after the stamp would reach the limit, so a beat due just then counts."""
IDLE_LOOK_S = 0.05
"""How often the record is read before the daemon's first beat and after its last."""


class GuardedOutputs(Protocol):
    """What the guard needs of the supervisor's HAL: the relays as the image has them, and
    a way to drop them (from this thread, at any time)."""

    def energised(self) -> bool: ...

    def force_all_outputs_safe(self) -> None: ...


GUARD_LATE_S = 0.02
"""The guard looked this much later than it meant to: it was stopped or starved itself (a
frozen supervisor), and vouches for nothing it did not see."""


@dataclass(frozen=True)
class Stall:
    """A scan that stopped: whose (pid), since when (the last stamp), and what was done."""

    pid: int
    beat_ns: int
    stalled_s: float
    energised: bool
    """A relay was on in the image when the guard looked (it made them safe)."""
    was_on: bool = False
    """The stalled scan's last write left a relay on (the beat record says)."""
    guard_late_s: float = 0.0
    """How much later than planned the guard looked: its own freeze, if any."""

    def outputs(self) -> str:
        """What the supervisor knows of the relays over the stall, in words: "off" only when
        they were off from the last cycle on; otherwise how long they may have been on."""
        late = self.guard_late_s
        itself = f"; the supervisor itself was stopped {late:.2f} s" if late > GUARD_LATE_S else ""
        if self.energised:
            return (
                f"energised, made safe by the supervisor {self.stalled_s:.2f} s after the"
                f" daemon's last cycle{itself}"
            )
        if self.was_on:
            return (
                f"on at the daemon's last cycle and off {self.stalled_s:.2f} s later, when the"
                f" supervisor looked: on for up to {self.stalled_s:.2f} s as far as it"
                f" knows{itself}"
            )
        return "off"


def armed(beat: Beat) -> bool:
    """A daemon's scan to guard: stamped (its first cycle done), not finished, with a limit."""
    return beat.beat_ns != 0 and not beat.finished and beat.limit_ns != 0


class OutputGuard(TimedThread):
    """Watches the shared record on a thread of its own; `on_trip` hears of a danger it made
    safe, `on_hang` of a scan stopped past `hang_s` (both on this thread: never block)."""

    def __init__(
        self,
        reader: BeatReader,
        outputs: GuardedOutputs,
        *,
        on_trip: Callable[[Stall], None],
        on_hang: Callable[[Stall], None],
        hang_s: float,
        after_safe: Callable[[], None] | None = None,
        after_look: Callable[[int], None] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        super().__init__("output-guard")
        self.reader = reader
        self.outputs = outputs
        self.on_trip = on_trip
        self.on_hang = on_hang
        self.after_safe = after_safe
        """Called right after the safe image is written (the simulated world steps on it)."""
        self.after_look = after_look
        """Called after each look, with its time: this thread ran and read the record (the
        supervisor tells systemd it is alive, sdnotify.py)."""
        self.hang_ns = round(hang_s * 1e9)
        self.clock_ns = clock_ns
        self.trips = 0
        self.stalls = 0
        self._stall: Stall | None = None
        self._hung_reported: int | None = None

    def _run(self) -> None:
        set_sched_slice(SCHED_SLICE_NS)  # wake at once beside a busy neighbour (runner.py)
        wait = IDLE_LOOK_S
        due = self.clock_ns() + round(wait * 1e9)
        while self.sleep(wait):
            now = self.clock_ns()
            wait = self.look(self.reader.read(), now, max(0, now - due))
            if self.after_look is not None:
                self.after_look(now)
            due = now + round(wait * 1e9)

    def stalled(self) -> bool:
        """The record shows a scan that has stopped now: armed, not finished, its stamp older
        than its limit (from any thread: one read of the shared record)."""
        beat = self.reader.read()
        return armed(beat) and self.clock_ns() - beat.beat_ns > beat.limit_ns

    def look(self, beat: Beat, now_ns: int, late_ns: int = 0) -> float:
        """One look at the record, `late_ns` after it was due; the seconds until the next
        (public for tests)."""
        if not armed(beat):
            self._stall = None
            return IDLE_LOOK_S
        age = now_ns - beat.beat_ns
        if age <= beat.limit_ns:
            if self._stall is not None:
                self._resumed(self._stall, beat)
            return (beat.beat_ns + beat.limit_ns - now_ns) / 1e9 + MARGIN_S
        stall = self._stall
        if stall is None or stall.beat_ns != beat.beat_ns or stall.pid != beat.pid:
            stall = self._stalled(beat, age, late_ns / 1e9)
        elif stall.energised and self.outputs.energised():
            self._make_safe()  # written again while latched (a write in flight at the trip)
        if age > self.hang_ns and self._hung_reported != beat.beat_ns:
            self._hung_reported = beat.beat_ns
            self.on_hang(dataclasses.replace(stall, stalled_s=age / 1e9))
        until_hang = (beat.beat_ns + self.hang_ns - now_ns) / 1e9
        return max(MARGIN_S, min(beat.limit_ns / 1e9, until_hang + MARGIN_S))

    def _stalled(self, beat: Beat, age_ns: int, late_s: float) -> Stall:
        energised = self.outputs.energised()
        stall = Stall(beat.pid, beat.beat_ns, age_ns / 1e9, energised, beat.energised, late_s)
        self._stall = stall
        self.stalls += 1
        if energised:
            self.reader.latch()  # first: a daemon that wakes now writes only the safe state
            self._make_safe()
            self.trips += 1
            self.on_trip(stall)
        elif beat.energised:  # off now, on at the last cycle: say what is not known
            log.error(
                "event=daemon_stalled pid=%d stalled_s=%.4f outputs=on_then_off on_up_to_s=%.4f"
                " guard_late_s=%.4f action=none detail=%r",
                beat.pid,
                stall.stalled_s,
                stall.stalled_s,
                late_s,
                stall.outputs(),
            )
        else:
            log.warning(
                "event=daemon_stalled pid=%d stalled_s=%.4f outputs=off action=none",
                beat.pid,
                stall.stalled_s,
            )
        return stall

    def _make_safe(self) -> None:
        self.outputs.force_all_outputs_safe()
        if self.after_safe is not None:
            self.after_safe()

    def _resumed(self, stall: Stall, beat: Beat) -> None:
        self._stall = None
        log.info(
            "event=daemon_resumed pid=%d stalled_s=%.4f latched=%s",
            stall.pid,
            (beat.beat_ns - stall.beat_ns) / 1e9,
            "yes" if beat.latched else "no",
        )
