"""The one door from production to the simulator wing (`sim`).

The daemon, the supervisor and `machine demo` reach the simulator only here, and only when it
is configured: each function imports `sim` on use, so a hardware install never loads it, and
the rest of service/ sees a `Hal` and the bus's `SimPort` (tests/test_layering.py pins this).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Protocol

from hal.base import Hal
from service.bus.injection import SimPort
from service.config.model import MachineConfig


class World(SimPort, Protocol):
    """The simulated world behind a process image, as the supervisor runs it."""

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def step_now(self) -> None: ...


def sim_hal(config: MachineConfig) -> Hal:
    """The simulator HAL, on the real clock (an injected scan stall really sleeps)."""
    from sim.hal import SimHal

    return SimHal(time.monotonic, config.hal.iomap, config.hal.sim, sleep=time.sleep)


def sim_port(hal: Hal) -> SimPort | None:
    """The simulator behind `hal` as the bus's `SimPort`; None for a hardware backend."""
    if "sim.hal" not in sys.modules:
        return None  # never loaded: no simulator runs in this process
    from sim.faults import HalSim
    from sim.hal import SimHal

    return HalSim(hal) if isinstance(hal, SimHal) else None


def sim_world(config: MachineConfig, directory: Path, period_s: float) -> tuple[World, str, str]:
    """The world on a fresh process image in `directory`, stepped every `period_s`; with the
    image file and the piCtory config the daemon's RevPi backend opens on it."""
    from sim.world import CONFIG_RSC, SimWorld, make_image

    procimg = make_image(directory / "procimg")
    world = SimWorld(config.hal.iomap, procimg, str(CONFIG_RSC), config.hal.sim, period_s)
    return world, procimg, str(CONFIG_RSC)


def run_demo(config: MachineConfig, speed: float) -> int:
    """`machine demo`: one whole session on the simulator in the terminal."""
    from sim.demo import run_demo as demo

    return demo(config, speed=speed)
