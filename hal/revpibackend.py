"""The Revolution Pi as a HAL backend: registered as `revpi` in pyproject.toml (`hal.backends`)."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict

from .backends import Clock, Simulator, Sleep, World
from .base import Hal
from .iomap import IoMap


class RevPiSettings(BaseModel):
    """`[hal.revpi]`: where revpimodio2 finds the process image and the piCtory config."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    procimg: str = "/dev/piControl0"
    configrsc: str | None = None
    hw_watchdog: bool = False
    """Toggle the base module's hardware watchdog bit from the scan loop (RevPi Connect: a
    MAX6370 that power-cycles the box after 60 s without a toggle, once its WD jumper is
    removed; docs/revpi.md). Off by default: an armed watchdog resets the box while nothing
    toggles it (updates, a stopped daemon)."""


class RevPiBackend:
    """`RevPiHal` on the configured process image; nothing simulated."""

    settings = RevPiSettings

    def open(self, iomap: IoMap, settings: object, clock: Clock, sleep: Sleep | None) -> Hal:
        # On use: the config reads `settings` in every process, and the simulator never
        # needs the RevPi backend's 800 lines (which load revpimodio2 on use in their turn).
        from .revpi import RevPiHal

        rp = RevPiSettings.model_validate(settings)
        return RevPiHal(iomap, rp.procimg, rp.configrsc, hw_watchdog=rp.hw_watchdog)

    def simulator(self, hal: Hal) -> Simulator | None:
        return None

    def world(
        self, iomap: IoMap, settings: object, directory: Path, period_s: float, attach: bool = False
    ) -> World | None:
        return None


BACKEND = RevPiBackend()
