"""The IO map: which HAL channel each logical IO of the ride is wired to."""

from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field


class Signal(StrEnum):
    """The logical IO points of the two-axis ride."""

    ROTATE_HOME = "rotateHome"
    TILT_HOME = "tiltHome"
    ESTOP = "estop"
    TILT_POSITION = "tiltPosition"
    ROTATE_RELAY = "rotateRelay"
    ROTATE_DIR = "rotateDir"
    TILT_RELAY = "tiltRelay"
    TILT_DIR = "tiltDir"
    CHARGE_PUMP = "chargePump"


DIGITAL_INPUTS = (Signal.ROTATE_HOME, Signal.TILT_HOME, Signal.ESTOP)
ANALOG_INPUTS = (Signal.TILT_POSITION,)
RELAY_OUTPUTS = (Signal.ROTATE_RELAY, Signal.ROTATE_DIR, Signal.TILT_RELAY, Signal.TILT_DIR)
OPTIONAL_OUTPUTS = (Signal.CHARGE_PUMP,)
"""Outputs a ride may have: the charge pump, which the scan toggles while it is healthy and an
external watchdog relay needs to keep the drives powered (docs/revpi.md)."""


class IoMap(BaseModel):
    """Logical name → channel (a piCtory IO name on a Revolution Pi, e.g. `I_1`).

    The E-stop is wired normally closed by default (`estop_active_low`): a broken wire reads as
    pressed, as a safety input must.
    """

    model_config = ConfigDict(extra="forbid", populate_by_name=True, frozen=True)

    rotate_home: str = Field(default="I_1", alias="rotateHome", min_length=1)
    tilt_home: str = Field(default="I_2", alias="tiltHome", min_length=1)
    estop: str = Field(default="I_3", min_length=1)
    tilt_position: str = Field(default="InputValue_1", alias="tiltPosition", min_length=1)
    rotate_relay: str = Field(default="O_1", alias="rotateRelay", min_length=1)
    rotate_dir: str = Field(default="O_2", alias="rotateDir", min_length=1)
    tilt_relay: str = Field(default="O_3", alias="tiltRelay", min_length=1)
    tilt_dir: str = Field(default="O_4", alias="tiltDir", min_length=1)
    charge_pump: str | None = Field(default=None, alias="chargePump", min_length=1)
    """A digital output the scan toggles every cycle while it is healthy and nothing is
    faulted; unset: the ride has no charge pump (docs/revpi.md)."""
    estop_active_low: bool = True

    def channel(self, signal: Signal) -> str:
        """The channel a logical signal is wired to (an optional one must be mapped)."""
        value: str | None = getattr(self, _FIELD[signal])
        if value is None:
            raise KeyError(f"{signal.value} is not mapped")
        return value

    def channels(self, signals: tuple[Signal, ...]) -> list[str]:
        return [self.channel(s) for s in signals]

    def mapped(self) -> list[Signal]:
        """Every signal wired to a channel: all the ride's, and the optional ones mapped."""
        return [s for s in Signal if getattr(self, _FIELD[s]) is not None]


_FIELD = {
    Signal.ROTATE_HOME: "rotate_home",
    Signal.TILT_HOME: "tilt_home",
    Signal.ESTOP: "estop",
    Signal.TILT_POSITION: "tilt_position",
    Signal.ROTATE_RELAY: "rotate_relay",
    Signal.ROTATE_DIR: "rotate_dir",
    Signal.TILT_RELAY: "tilt_relay",
    Signal.TILT_DIR: "tilt_dir",
    Signal.CHARGE_PUMP: "charge_pump",
}
