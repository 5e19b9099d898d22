"""The simulator as a HAL backend: registered as `sim` in pyproject.toml (`hal.backends`)."""

from __future__ import annotations

from pathlib import Path

from ride_machine.hal.backends import Clock, Simulator, Sleep, World
from ride_machine.hal.base import Hal
from ride_machine.hal.iomap import IoMap

from .settings import PhysicsParams


class SimBackend:
    """`SimHal` on the loop's clock, or the plant behind a process image for the supervisor
    (a process of its own: `sim.plant`)."""

    settings = PhysicsParams

    # The physics and the world are imported on use: the config reads `settings` in every
    # process, on hardware too, and a hardware daemon never loads the simulator.
    def open(self, iomap: IoMap, settings: object, clock: Clock, sleep: Sleep | None) -> Hal:
        from .hal import SimHal

        return SimHal(clock, iomap, PhysicsParams.model_validate(settings), sleep=sleep)

    def simulator(self, hal: Hal) -> Simulator | None:
        from .faults import HalSim
        from .hal import SimHal

        return HalSim(hal) if isinstance(hal, SimHal) else None

    def world(
        self, iomap: IoMap, settings: object, directory: Path, period_s: float, attach: bool = False
    ) -> World:
        from .plant_link import PlantProcess

        params = PhysicsParams.model_validate(settings)
        return PlantProcess(iomap, params, directory, period_s, attach=attach)


BACKEND = SimBackend()
