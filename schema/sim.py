"""Fault injection requests for `machine/<id>/sim/<fault>` (simulator backend only)."""

from __future__ import annotations

from enum import StrEnum
from typing import Literal

from pydantic import Field

from .base import OpenWireModel, WireModel
from .commands import TransactionId


class SimAxis(StrEnum):
    ROTATE = "rotate"
    TILT = "tilt"


class SwitchState(StrEnum):
    OPEN = "open"
    CLOSED = "closed"


class SimEstop(WireModel):
    """`sim/estop`: press or release the E-stop."""

    transaction_id: TransactionId | None = None
    pressed: bool


class SimHomeSwitch(WireModel):
    """`sim/home`: stick a home switch open or closed (`stuck: null` repairs it)."""

    transaction_id: TransactionId | None = None
    axis: SimAxis = Field(strict=False)
    stuck: SwitchState | None = Field(default=None, strict=False)


class SimTiltSignal(WireModel):
    """`sim/tilt_ai`: freeze the tilt analog input or add noise (counts, uniform ±)."""

    transaction_id: TransactionId | None = None
    frozen: bool = False
    noise_counts: float = Field(default=0.0, ge=0.0, le=30000.0)


class SimStall(WireModel):
    """`sim/stall`: a drive that gets power but does not move."""

    transaction_id: TransactionId | None = None
    axis: SimAxis = Field(strict=False)
    stalled: bool = True


class SimStalls(WireModel):
    """`sim/stalls`: each scan stalls with `probability` for up to `max_s` (uniform) before
    writing its outputs, the old ones running on (a busy host); 0 ends it."""

    transaction_id: TransactionId | None = None
    probability: float = Field(default=0.0, ge=0.0, le=1.0)
    max_s: float = Field(default=0.05, ge=0.0, le=1.0)


class SimPlace(WireModel):
    """`sim/place`: put an axis where a ride may be found in the morning (null: leave it)."""

    transaction_id: TransactionId | None = None
    tilt_deg: float | None = Field(default=None, ge=-90.0, le=180.0)
    rotate_deg: float | None = Field(default=None, ge=-3600.0, le=3600.0)


class SimClear(WireModel):
    """`sim/clear`: repair every injected fault (the E-stop stays as it is)."""

    transaction_id: TransactionId | None = None


class SimWorldState(OpenWireModel):
    """What the simulated world looks like: the truth the controller cannot see."""

    kind: Literal["world"] = "world"
    time: float
    tilt_deg: float
    rotate_deg: float
    revolutions: float
    estop_pressed: bool
    relays: dict[str, bool]
    faults: dict[str, object]
    tilt_home_closed: bool | None = None
    """The tilt switch's contact (before a stuck fault), for comparing with what was read."""
    rotate_home_closed: bool | None = None
    tilt_zero_counts: float | None = None
    """The analog value at the tilt switch's closing edge: what a tilt calibration's offset
    should measure."""
    stalled_s: float | None = None
    """Time the injected scan stalls took so far."""
    late_steps: int | None = None
    """Steps of a world on its own thread (`machine supervise --sim`) that came later than
    planned, so far: the daemon read the field's sensors unchanged meanwhile. None for the
    embedded simulator, which the scan steps itself and which is never late."""
    longest_late_s: float | None = None
    """The latest of those steps, seconds behind its plan."""
    drives_powered: bool | None = None
    """Whether the charge pump's external relay gives the drives power; None: the ride has no
    charge pump (no `chargePump` in the IO map)."""
    drives_off_s: float | None = None
    """How long the drives have been without power at `clock` (0 while powered)."""
    charge_pump_drops: int | None = None
    """Times the charge pump's relay dropped the drives and was picked up again."""
    clock: float | None = None
    """The world's own clock at this report: for a world on its own (`machine supervise
    --sim`) the host's CLOCK_MONOTONIC in seconds, which every process on the host shares, so
    the drives were cut at `clock - drives_off_s`."""


SIM_REQUESTS: dict[str, type[WireModel]] = {
    "estop": SimEstop,
    "home": SimHomeSwitch,
    "tilt_ai": SimTiltSignal,
    "stall": SimStall,
    "clear": SimClear,
    "stalls": SimStalls,
    "place": SimPlace,
}
