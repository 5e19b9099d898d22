"""The ride's physics, with fault injection: shared by the simulator HAL and the process-image
world. Its parameters are the `[hal.sim]` section of machine.toml (`service.config.model`)."""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from enum import StrEnum

from service.config.model import PhysicsParams

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
class World:
    """Positions of both axes, advanced by `step(dt)` under the current drive outputs.

    E-stop cuts drive power (as a safety relay does), so nothing moves while it is pressed,
    whatever the outputs say.
    """

    params: PhysicsParams = field(default_factory=PhysicsParams)
    faults: Faults = field(default_factory=Faults)
    drive: Drive = field(default_factory=Drive)
    rotate_deg: float = 0.0
    rotate_travel_deg: float = 0.0
    tilt_deg: float = 0.0
    time: float = 0.0
    _frozen_raw: int | None = None
    _rng: random.Random = field(default_factory=random.Random)

    def __post_init__(self) -> None:
        self.rotate_deg = self.params.start_rotate_deg % 360.0
        self.tilt_deg = self.params.start_tilt_deg
        self._rng.seed(self.params.seed)

    @property
    def revolutions(self) -> float:
        """Signed revolutions travelled since start-up (CW positive)."""
        return self.rotate_travel_deg / 360.0

    def step(self, dt: float) -> None:
        """Advance the mechanics by `dt` seconds."""
        if dt <= 0:
            return
        self.time += dt
        if self.faults.estop_pressed:
            return
        p = self.params
        if self.drive.rotate_on and not self.faults.rotate_stalled:
            delta = p.rotate_speed_dps * dt * (-1.0 if self.drive.rotate_ccw else 1.0)
            self.rotate_travel_deg += delta
            self.rotate_deg = (self.rotate_deg + delta) % 360.0
        if self.drive.tilt_on and not self.faults.tilt_stalled:
            delta = p.tilt_speed_dps * dt * (1.0 if self.drive.tilt_up else -1.0)
            self.tilt_deg = min(p.tilt_max_deg, max(p.tilt_min_deg, self.tilt_deg + delta))

    def still(self) -> tuple[object, ...] | None:
        """Everything `sense` reads, while nothing changes by itself: no relay on (so `step`
        moves nothing) and no noise (so `sense` draws nothing). None otherwise. Two equal
        results mean `sense` reads exactly the same twice, so a scan may reuse its image."""
        d, f = self.drive, self.faults
        if d.rotate_on or d.tilt_on or f.tilt_ai_noise_counts:
            return None
        return (
            self.rotate_deg,
            self.tilt_deg,
            f.estop_pressed,
            f.rotate_home,
            f.tilt_home,
            f.tilt_ai_frozen,
            self.params,
        )

    def sense(self) -> WorldInputs:
        """Read every sensor, faults applied."""
        p, f = self.params, self.faults
        rotate_home = self.rotate_deg < p.home_arc_deg
        tilt_home = self.tilt_deg <= p.tilt_home_deg
        return WorldInputs(
            rotate_home=_switch(rotate_home, f.rotate_home),
            tilt_home=_switch(tilt_home, f.tilt_home),
            estop_pressed=f.estop_pressed,
            tilt_raw=self._tilt_raw(),
        )

    def _tilt_raw(self) -> int:
        p, f = self.params, self.faults
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
