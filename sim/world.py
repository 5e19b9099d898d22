"""The simulated ride as a real-time world behind a process image, for `machine supervise --sim`.

The daemon drives it through the same process-image file as real RevPi hardware, and it runs in
a plant process of its own (`sim.plant`), so it keeps running (and can be observed) while the
daemon dies and restarts, and while the whole controller is frozen.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

from pydantic import BaseModel

from ride_machine.hal.base import HalError
from ride_machine.hal.iomap import IoMap
from ride_machine.schema.sim import SimWorldState
from ride_machine.sim import faults as simfaults

from .procimg import ProcImgSim
from .settings import PhysicsParams

log = logging.getLogger(__name__)

CONFIG_RSC = Path(__file__).with_name("config.rsc")
"""The piCtory config (Core + DIO + AIO) the simulated world is wired by."""
IMAGE_BYTES = 4096
"""The size of piControl's process image."""
LATE_S = 0.015
"""A step this much later than planned is counted and logged: the daemon saw the field's
sensors unchanged that long (piControl on a real RevPi is never late so). Low enough to count
every lateness that can spoil the tilt's speed check: the tests' fast config judges it over
0.1 s within 30 %, so a reading 0.03 s staler at a window's end than at its start reads as a
slow drive, and a reading on time is already up to one 10 ms period old (a quiet run on a slow
host met a tilt "58.4°/s" against 90 ± 30 % with a world late under the 0.03 s counted before)."""
ARC_HOLD_MAX_S = 0.5
"""How long the rotate may wait in its home arc for the daemon's scan to see the switch closed
(`SimWorld.follow_scans`): long enough for the scan stalls of a loaded host, short of a frozen
daemon, which the world lets turn on as a real ride would."""


def make_image(path: Path) -> str:
    """A fresh, all-zero process-image file (every output off)."""
    path.write_bytes(bytes(IMAGE_BYTES))
    return str(path)


class SimWorld:
    """`ProcImgSim` stepped every `period_s` on its own thread; faults land between steps."""

    def __init__(
        self,
        iomap: IoMap,
        procimg: str,
        configrsc: str,
        params: PhysicsParams,
        period_s: float,
        clock: Callable[[], float] = time.monotonic,
        spawn: Callable[..., threading.Thread] = threading.Thread,
    ) -> None:
        """`spawn` makes the thread the world runs on (the supervisor's names itself for the
        OS)."""
        self.period = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self._sim = ProcImgSim(iomap, procimg, configrsc, clock, params)
        self.procimg, self.configrsc = procimg, configrsc
        """The image and the piCtory config the daemon's RevPi backend opens on this world."""
        self._spawn = spawn
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.failures = 0
        self.late_steps = 0
        """Steps later than `LATE_S` (a loaded host kept this thread from running)."""
        self.longest_late_s = 0.0
        self._late_logged = -1.0e9
        self._scans: Callable[[], int] | None = None
        self._closed_at: tuple[float, int] | None = None
        """When the image first showed the rotate's home switch closed, and the daemon's
        completed scans then."""

    def start(self) -> None:
        self._thread = self._spawn(target=self._run, name="sim-world", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self._lock:
            self._sim.close()

    def step_now(self) -> None:
        """One step at once, e.g. so the world has seen outputs the supervisor just dropped."""
        with self._lock:
            self._step()

    def follow_scans(self, scans: Callable[[], int]) -> None:
        """Hold the rotate in its home arc (1° short of its far end) until a scan that began
        after the image showed the switch closed has completed (`scans()` passed the count then
        by two), for up to `ARC_HOLD_MAX_S`. At the tests' 720°/s the switch is closed 0.042 s
        a turn, less than a loaded host stalls a scan: the embedded world, stepped by the scan,
        never lets a stall hide the edge (`World._unskipped`), and this world now does not either.
        A real ride does not wait; its watchdog limit is shorter than its arc (machine
        validate)."""
        self._scans = scans

    def decode(self, what: str, payload: bytes, encoding: str | None) -> BaseModel:
        return simfaults.decode_request(what, payload, encoding)

    def apply(self, request: BaseModel) -> None:
        """Inject (or repair) a fault decoded from a `sim/<fault>` request."""
        with self._lock:
            simfaults.apply_fault(self._sim.ride, request)

    def world(self, stamp: float) -> SimWorldState:
        with self._lock:
            state = simfaults.world_state(self._sim.ride, stamp)
            return state.model_copy(
                update={"late_steps": self.late_steps, "longest_late_s": self.longest_late_s}
            )

    def relays(self) -> dict[str, bool]:
        with self._lock:
            return dict(self._sim.relays())

    def _run(self) -> None:
        deadline = self._clock()
        while not self._stop.is_set():
            now = self._clock()
            self._late(now, now - deadline)
            with self._lock:
                self._step()
            deadline += self.period
            delay = deadline - self._clock()
            if delay < 0:
                deadline = self._clock()  # fell behind (a loaded host): no burst of steps
                delay = 0.0
            self._stop.wait(delay)

    def _late(self, now: float, late_s: float) -> None:
        """Count and log a step later than `LATE_S`: a fault the daemon raised meanwhile (a
        tilt that did not follow) may be the simulated field's, not the daemon's."""
        if late_s <= LATE_S:
            return
        self.late_steps += 1
        self.longest_late_s = max(self.longest_late_s, late_s)
        if now - self._late_logged < 1.0:  # at most once a second on a host that stays busy
            return
        self._late_logged = now
        log.warning(
            "event=sim_world_late late_s=%.3f late_steps=%d (the simulated sensors stood still"
            " that long)",
            late_s,
            self.late_steps,
        )

    def _step(self) -> None:
        if self._sim.closed:
            return
        world = self._sim.world
        world.hold_in_arc = self._holding()
        gap = self._clock() - self._sim.time
        if world.pump is not None and gap > world.pump.timeout_s / 2:
            world.pump.unseen(world.time, world.time + gap)  # this thread came late
        try:
            self._sim.step()
        except HalError as exc:
            self.failures += 1
            if self.failures == 1:
                log.error("event=sim_world_step_failed error=%r", str(exc))
        else:
            self.failures = 0
            if not world.rotate_switch.closed:
                self._closed_at = None
            elif self._closed_at is None and self._scans is not None:
                self._closed_at = (self._clock(), self._scans())

    def _holding(self) -> bool:
        if self._closed_at is None or self._scans is None:
            return False
        since, scans = self._closed_at
        return self._clock() - since < ARC_HOLD_MAX_S and self._scans() < scans + 2
