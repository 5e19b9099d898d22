"""`[hal.sim]`: the simulated machine's mechanics, as machine.toml spells them.

The simulator backend registers this model (`sim.backend`), and the machine config validates
`[hal.sim]` with whatever model the backend named `sim` registers (`hal.backends`): the config
never imports the simulator. It imports pydantic only, so reading it loads no physics.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class PhysicsParams(BaseModel):
    """`[hal.sim]`: the simulated machine's mechanics (the controller must not know the AI
    gain/offset)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rotate_speed_dps: float = Field(default=90.0, gt=0, le=3600)
    home_arc_deg: float = Field(default=10.0, gt=0, lt=180)
    tilt_speed_dps: float = Field(default=15.0, gt=0, le=360)
    tilt_min_deg: float = -5.0
    tilt_max_deg: float = 95.0
    tilt_home_deg: float = Field(default=0.0, ge=-5, le=10)
    ai_offset_counts: float = 1200.0
    ai_gain_counts_per_deg: float = 40.0
    start_rotate_deg: float = 137.0
    start_tilt_deg: float = 12.0
    seed: int = 1
    tilt_home_hysteresis_deg: float = Field(default=0.0, ge=0, le=10)
    """The tilt switch closes going down at `tilt_home_deg` and opens going up this much higher."""
    rotate_home_hysteresis_deg: float = Field(default=0.0, ge=0, le=30)
    """The rotate switch, once closed, opens only this far outside its arc (either side)."""
    tilt_home_bounce_s: float = Field(default=0.0, ge=0, le=0.1)
    """After each change the tilt switch reads at random for this long (contact bounce)."""
    rotate_home_bounce_s: float = Field(default=0.0, ge=0, le=0.1)
    tilt_noise_counts: float = Field(default=0.0, ge=0, le=30000)
    """Analog noise from power-up (uniform ±counts); `sim/tilt_ai` changes it at run time."""
    scan_stall_probability: float = Field(default=0.0, ge=0, le=1)
    """Each scan, the chance that the scan thread stalls before writing its outputs …"""
    scan_stall_max_s: float = Field(default=0.0, ge=0, le=1)
    """… for a uniform random time up to this (`sim/stalls` changes both at run time)."""
    charge_pump_timeout_s: float = Field(default=0.1, gt=0, le=10)
    """With a `chargePump` channel in the IO map: the external watchdog relay keeps the drives
    powered only this long after the charge-pump output last changed (docs/revpi.md)."""
