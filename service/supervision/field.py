"""The supervisor's side of the field: its own path to the process image, to write the ride's
outputs safe whatever the daemon does, and with the simulator the plant the daemon drives
through that image (a process of its own, started here or found where it already runs)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from ride_machine.hal.backends import World, backend
from ride_machine.hal.base import HalConfigError
from ride_machine.schema.findings import Finding, Severity
from ride_machine.service.config.model import HalBackend, MachineConfig
from ride_machine.service.core.scan.beat import CYCLES_OFFSET


class SafeOutputs(Protocol):
    """What the supervisor needs from a HAL: read and drop the outputs, from any thread."""

    def energised(self) -> bool: ...

    def force_all_outputs_safe(self) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Field:
    """The safe-output path, the simulated plant (None on hardware), and the config the daemon
    child runs with (the simulator's world as a RevPi process image)."""

    safe: SafeOutputs
    world: World | None
    child: MachineConfig


def open_field(
    config: MachineConfig, directory: Path, plant: Path | None, period_s: float, beat_fd: int
) -> Field:
    """Open the safe-output path (outputs safe at once) and, with the simulator, start the plant
    in `directory` (or find the one running in `plant`), which reads the daemon's scan count
    from the beat record `beat_fd`."""
    from ride_machine.hal.revpi import RevPiHal  # revpimodio2 is an optional extra: import on use

    directory.mkdir(parents=True, exist_ok=True)
    hal = config.hal
    world = backend(hal.backend).world(
        hal.iomap, hal.settings(), plant or directory, period_s, plant is not None
    )
    if plant is not None and world is None:
        raise HalConfigError([_plant_needs_sim(hal.backend)])
    try:
        if world is not None:  # a simulated world: the child drives it as a RevPi
            world.follow_beat(beat_fd, CYCLES_OFFSET)
            revpi = {"procimg": world.procimg, "configrsc": world.configrsc}
            config = config.with_overrides(hal={"backend": HalBackend.REVPI, "revpi": revpi})
        rp = config.hal.revpi
        safe = RevPiHal(config.hal.iomap, rp.procimg, rp.configrsc)  # opens safe
        if world is not None:
            world.start()
    except BaseException:
        if world is not None:
            world.stop()
        raise
    child = config.model_copy(update={"data_dir": str(Path(config.data_dir).resolve())})
    return Field(safe, world, child)


def _plant_needs_sim(name: str) -> Finding:
    return Finding(
        category="hal",
        severity=Severity.ERROR,
        path="/hal/backend",
        message=f"--plant attaches to a simulated plant; the {name!r} backend has none (--sim)",
    )
