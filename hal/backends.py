"""HAL backends by name: the one lookup (`backend`), over the `ride_machine.hal` entry points.

ros2_control loads its hardware by name (pluginlib); a Python package does it with entry points,
as the zenoh CLI finds our msgpack codec. pyproject.toml registers the project's backends
(`sim`: the simulator, `revpi`: a Revolution Pi); the machine config, the daemon and the
supervisor reach a backend only through `backend(name)`, so the code that runs never imports
the code that simulates (tests/test_layering.py holds the arrows).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path
from typing import Protocol, runtime_checkable

from pydantic import BaseModel

from ride_machine.schema.sim import SimWorldState

from .base import Hal
from .iomap import IoMap

GROUP = "ride_machine.hal"
"""The entry-point group a backend registers in (`[project.entry-points]` of pyproject.toml)."""

Clock = Callable[[], float]
Sleep = Callable[[float], object]


class Simulator(Protocol):
    """Fault injection into a simulated world, as `machine/<id>/sim/<fault>` serves it."""

    def decode(self, what: str, payload: bytes, encoding: str | None) -> BaseModel:
        """The request for `sim/<what>`; `schema.codec.DecodeError`, carrying the wire `Error`,
        for an unknown key or a payload that is no such request."""
        ...

    def apply(self, request: BaseModel) -> None:
        """Inject (or repair) the fault a decoded request asks for."""
        ...

    def world(self, stamp: float) -> SimWorldState:
        """The simulated world, as the `sim/world` reply reports it."""
        ...


class World(Simulator, Protocol):
    """A simulated plant behind a process image (`machine supervise`), on a clock of its own
    that no freeze of the controller stops: the daemon drives it with the RevPi backend on
    `procimg` and `configrsc`."""

    procimg: str
    configrsc: str

    @property
    def pid(self) -> int | None:
        """The plant's own process, once started (None: it runs in this one)."""
        ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def step_now(self) -> None:
        """One step at once (so the world has seen outputs just dropped)."""
        ...

    def follow_beat(self, fd: int, offset: int) -> None:
        """The daemon's completed scans, a uint64 at `offset` of the shared memory `fd` (its
        beat record), for a world that waits for a scan to see a switch the embedded world
        would not let a stall hide."""
        ...


@runtime_checkable
class Backend(Protocol):
    """A HAL backend: the model of its `[hal.<name>]` table, the HAL it opens, and the
    simulated world behind it, if it has one."""

    @property
    def settings(self) -> type[BaseModel]:
        """The model of this backend's `[hal.<name>]` table in machine.toml."""
        ...

    def open(self, iomap: IoMap, settings: object, clock: Clock, sleep: Sleep | None) -> Hal:
        """The HAL, outputs safe; `HalConfigError`, `HalError` or `OSError` when it cannot open.
        `sleep` is how an injected scan stall passes (None: none passes)."""
        ...

    def simulator(self, hal: Hal) -> Simulator | None:
        """Fault injection into the world behind `hal` (a HAL this backend opened); None for
        hardware."""
        ...

    def world(
        self, iomap: IoMap, settings: object, directory: Path, period_s: float, attach: bool = False
    ) -> World | None:
        """A world behind a fresh process image in `directory`, stepped every `period_s` by
        a process of its own once it starts (`attach`: one already running in `directory`,
        started by someone else); None for hardware."""
        ...


class NoBackend(LookupError):
    """No backend is registered under the name (or the project is not installed: its entry
    points are its registration, `pip install -e .`)."""


@functools.cache
def backend(name: str) -> Backend:
    """The backend registered as `name`, loaded once per process."""
    for point in entry_points(group=GROUP, name=name):
        found = point.load()
        if not isinstance(found, Backend):
            raise NoBackend(f"{point.value} (HAL backend '{name}') is not a backend")
        return found
    known = ", ".join(sorted(p.name for p in entry_points(group=GROUP))) or "none"
    raise NoBackend(
        f"no HAL backend '{name}' is registered (entry points {GROUP}: {known});"
        " install the project (pip install -e .)"
    )


@functools.cache
def names() -> frozenset[str]:
    """The registered backends' names, without loading any of them."""
    return frozenset(p.name for p in entry_points(group=GROUP))


def settings_of(name: str) -> type[BaseModel]:
    """The model of backend `name`'s `[hal.<name>]` table."""
    return backend(name).settings
