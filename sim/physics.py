"""The ride's physics, with fault injection: shared by the simulator HAL and the process-image
world. Its parameters are the `[hal.sim]` section of machine.toml (`sim.settings`)."""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from enum import StrEnum

from .settings import PhysicsParams

INT16_MIN, INT16_MAX = -32768, 32767


class SwitchFault(StrEnum):
    """A home switch that no longer follows the axis."""

    STUCK_OPEN = "stuck_open"
    STUCK_CLOSED = "stuck_closed"


@dataclass
class Faults:
    """Injected faults; all clear by default."""

    estop_pressed: bool = False
    rotate_home: SwitchFault | None = None
    tilt_home: SwitchFault | None = None
    tilt_ai_frozen: bool = False
    tilt_ai_noise_counts: float = 0.0
    tilt_ai_broken: int | None = None
    """The raw value a broken wire reads instead of the sensor (0: an open circuit,
    `INT16_MAX`: a short to the supply); None: the wiring is sound."""
    rotate_stalled: bool = False
    tilt_stalled: bool = False


@dataclass
class Drive:
    """The relay outputs as the physics sees them."""

    rotate_on: bool = False
    rotate_ccw: bool = False
    tilt_on: bool = False
    tilt_up: bool = False


@dataclass
class WorldInputs:
    """What the sensors show, before mapping onto channels."""

    rotate_home: bool
    tilt_home: bool
    estop_pressed: bool
    tilt_raw: int


@dataclass
class Switch:
    """A home switch's contact as the world holds it: closed or open, with hysteresis (its
    state changes only past the far side of the band) and bounce (after each change it reads
    at random for `bounce_s`, from the moment the axis crossed the threshold)."""

    closed: bool = False
    changed_at: float = float("-inf")

    def follow(self, closed: bool | None, at: float) -> None:
        """The contact at a new position: True/False where the position decides, None inside
        the hysteresis band (it keeps its state); `at` is when the threshold was crossed."""
        if closed is not None and closed != self.closed:
            self.closed, self.changed_at = closed, at

    def bouncing(self, now: float, bounce_s: float) -> bool:
        return now - self.changed_at < bounce_s


@dataclass
class ChargePumpRelay:
    """The external watchdog relay a charge pump feeds (LinuxCNC's name; a timer relay or a
    safety relay's dynamic input): the drives have power only while the controller's
    charge-pump output keeps changing, and lose it `timeout_s` after its last change; the
    next change picks the relay up again (retriggerable). No power before the first change.
    Times are the world's (`World.time`)."""

    timeout_s: float
    level: bool = False
    edge_at: float = -math.inf
    drops: int = 0
    """Times the relay dropped and was picked up again (a drop in progress not counted)."""

    @property
    def until(self) -> float:
        """When the drives lose power unless the output changes before."""
        return self.edge_at + self.timeout_s

    def powered(self, at: float) -> bool:
        return at <= self.until

    def feed(self, level: bool, at: float) -> None:
        """The output's level at `at`: a change retriggers the relay."""
        if level == self.level:
            return
        if self.edge_at > -math.inf and at > self.until:
            self.drops += 1
        self.level, self.edge_at = level, at

    def unseen(self, since: float, at: float) -> None:
        """The world did not look from `since` to `at` (its own thread came late on a busy
        host, which a hardware relay never does): changes then went unseen, so a relay that
        had power at `since` is taken as retriggered at `at`."""
        if self.powered(since):
            self.edge_at = max(self.edge_at, at)


@dataclass
class World:
    """Positions of both axes, advanced by `step(dt)` under the current drive outputs.

    E-stop cuts drive power (as a safety relay does), so nothing moves while it is pressed,
    whatever the outputs say. The tilt switch closes at `tilt_home_deg` going down and opens
    `tilt_home_hysteresis_deg` higher going up; the rotate switch closes over its arc and opens
    `rotate_home_hysteresis_deg` outside it.
    """

    params: PhysicsParams = field(default_factory=PhysicsParams)
    faults: Faults = field(default_factory=Faults)
    drive: Drive = field(default_factory=Drive)
    rotate_deg: float = 0.0
    rotate_travel_deg: float = 0.0
    tilt_deg: float = 0.0
    time: float = 0.0
    tilt_switch: Switch = field(default_factory=Switch)
    rotate_switch: Switch = field(default_factory=Switch)
    _frozen_raw: int | None = None
    pump: ChargePumpRelay | None = None
    """The charge pump's relay, when the ride has one: the drives move only while it holds."""
    hold_in_arc: bool = False
    """Set by the supervised world while the daemon's scan has not yet seen the rotate's home
    switch closed: the rotate turns on only to 1° short of the arc's far end (`_held`)."""
    _rng: random.Random = field(default_factory=random.Random)

    def __post_init__(self) -> None:
        self._rng.seed(self.params.seed)
        self.faults.tilt_ai_noise_counts = self.params.tilt_noise_counts
        self.place(self.params.start_tilt_deg, self.params.start_rotate_deg)

    @property
    def revolutions(self) -> float:
        """Signed revolutions travelled since start-up (CW positive)."""
        return self.rotate_travel_deg / 360.0

    def place(self, tilt_deg: float | None = None, rotate_deg: float | None = None) -> None:
        """Put the axes somewhere (a ride found there in the morning); a switch takes the
        state its region gives (open inside a hysteresis band), without bouncing."""
        p = self.params
        if tilt_deg is not None:
            self.tilt_deg = min(p.tilt_max_deg, max(p.tilt_min_deg, tilt_deg))
            self.tilt_switch = Switch(self.tilt_deg <= p.tilt_home_deg)
        if rotate_deg is not None:
            self.rotate_deg = rotate_deg % 360.0
            self.rotate_switch = Switch(self.rotate_deg < p.home_arc_deg)

    def step(self, dt: float) -> None:
        """Advance the mechanics by `dt` seconds."""
        if dt <= 0:
            return
        t0 = self.time
        self.time += dt
        if self.faults.estop_pressed:
            return
        if self.pump is not None:  # no drive power past the relay's drop-out
            dt = min(dt, self.pump.until - t0)
            if dt <= 0:
                return
        p = self.params
        if self.drive.rotate_on and not self.faults.rotate_stalled:
            v = p.rotate_speed_dps * (-1.0 if self.drive.rotate_ccw else 1.0)
            start = self.rotate_deg
            moved = math.copysign(self._held(self._unskipped(abs(v * dt))), v)
            self.rotate_travel_deg += moved
            self.rotate_deg = (start + moved) % 360.0
            self._rotate_contact(start, v, t0)
        if self.drive.tilt_on and not self.faults.tilt_stalled:
            v = p.tilt_speed_dps * (1.0 if self.drive.tilt_up else -1.0)
            start = self.tilt_deg
            self.tilt_deg = min(p.tilt_max_deg, max(p.tilt_min_deg, start + v * dt))
            self._tilt_contact(start, v, t0)

    def _unskipped(self, travel: float) -> float:
        """`travel` (degrees, unsigned), cut short in the middle of the home arc where it would
        pass the whole switch between two scans (a host that stalled the scan): the simulated
        rotate pauses there instead, so a session never turns a revolution too many. A real
        ride would not pause (docs/homing.md); only a gap that long makes the difference."""
        if self.rotate_switch.closed:
            return travel
        p = self.params
        ccw = self.drive.rotate_ccw
        to_close = (self.rotate_deg - p.home_arc_deg if ccw else -self.rotate_deg) % 360.0
        if travel < to_close + p.home_arc_deg + p.rotate_home_hysteresis_deg:
            return travel
        return to_close + p.home_arc_deg / 2

    def _held(self, travel: float) -> float:
        """`travel` (degrees, unsigned), cut short of the far end of the home arc while
        `hold_in_arc` and the switch is closed: the supervised world's pause for a scan that
        stalled across the arc, as `_unskipped` is the embedded world's (a real ride would not
        pause). Only a scan stalled for most of the arc's time meets it."""
        if not (self.hold_in_arc and self.rotate_switch.closed):
            return travel
        arc = self.params.home_arc_deg
        margin = min(1.0, arc / 4)
        stop = margin if self.drive.rotate_ccw else arc - margin
        ahead = (stop - self.rotate_deg + 180.0) % 360.0 - 180.0
        return min(travel, max(0.0, -ahead if self.drive.rotate_ccw else ahead))

    def _tilt_contact(self, start: float, v: float, t0: float) -> None:
        p, deg = self.params, self.tilt_deg
        closes, opens = p.tilt_home_deg, p.tilt_home_deg + p.tilt_home_hysteresis_deg
        state = True if deg <= closes else False if deg > opens else None
        edge = closes if state else opens
        self.tilt_switch.follow(state, t0 + (edge - start) / v)

    def _rotate_contact(self, start: float, v: float, t0: float) -> None:
        p, deg = self.params, self.rotate_deg
        h, arc = p.rotate_home_hysteresis_deg, p.home_arc_deg
        state = True if deg < arc else False if arc + h <= deg < 360.0 - h else None
        if state is None or state == self.rotate_switch.closed:
            return
        # The threshold crossed: CW the switch closes at 0 and opens at arc + h; CCW it
        # closes at arc and opens at -h.
        edge = {(True, True): 360.0, (True, False): arc + h, (False, True): arc}.get(
            (v > 0, state), 360.0 - h
        )
        travelled = (edge - start) % 360.0 if v > 0 else (start - edge) % 360.0
        self.rotate_switch.follow(state, t0 + travelled / abs(v))

    def still(self) -> tuple[object, ...] | None:
        """Everything `sense` reads, while nothing changes by itself: no relay on (so `step`
        moves nothing), no noise and no bounce (so `sense` draws nothing). None otherwise.
        Two equal results mean `sense` reads exactly the same twice, so a scan may reuse its
        image."""
        d, f, p = self.drive, self.faults, self.params
        if d.rotate_on or d.tilt_on or f.tilt_ai_noise_counts:
            return None
        if self.tilt_switch.bouncing(self.time, p.tilt_home_bounce_s):
            return None
        if self.rotate_switch.bouncing(self.time, p.rotate_home_bounce_s):
            return None
        return (
            self.rotate_deg,
            self.tilt_deg,
            self.rotate_switch.closed,
            self.tilt_switch.closed,
            f.estop_pressed,
            f.rotate_home,
            f.tilt_home,
            f.tilt_ai_frozen,
            f.tilt_ai_broken,
            self.params,
        )

    def sense(self) -> WorldInputs:
        """Read every sensor, faults applied."""
        p, f = self.params, self.faults
        return WorldInputs(
            rotate_home=_switch(
                self._contact(self.rotate_switch, p.rotate_home_bounce_s), f.rotate_home
            ),
            tilt_home=_switch(self._contact(self.tilt_switch, p.tilt_home_bounce_s), f.tilt_home),
            estop_pressed=f.estop_pressed,
            tilt_raw=self._tilt_raw(),
        )

    def _contact(self, switch: Switch, bounce_s: float) -> bool:
        if switch.bouncing(self.time, bounce_s):
            return self._rng.random() < 0.5
        return switch.closed

    def _tilt_raw(self) -> int:
        p, f = self.params, self.faults
        if f.tilt_ai_broken is not None:
            return f.tilt_ai_broken
        if f.tilt_ai_frozen and self._frozen_raw is not None:
            return self._frozen_raw
        raw = p.ai_offset_counts + p.ai_gain_counts_per_deg * self.tilt_deg
        if f.tilt_ai_noise_counts > 0:
            raw += self._rng.uniform(-f.tilt_ai_noise_counts, f.tilt_ai_noise_counts)
        value = max(INT16_MIN, min(INT16_MAX, round(raw)))
        self._frozen_raw = value
        return value


def _switch(actual: bool, fault: SwitchFault | None) -> bool:
    if fault is SwitchFault.STUCK_OPEN:
        return False
    if fault is SwitchFault.STUCK_CLOSED:
        return True
    return actual
