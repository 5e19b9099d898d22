"""`sim/<fault>`: the simulator's fault injection, through a small protocol.

The bus never imports the simulator: whoever assembles the daemon (or the supervisor) hands it
a `SimPort` (the `sim` package implements one); without one every `sim/*` key answers
NOT_AVAILABLE at once instead of leaving the caller to time out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from pydantic import BaseModel

from ride_machine.service.errors import NotAvailable

from .request import Request
from .routes import Route, Wildcard

WORLD = "world"
"""`sim/world`: read the world, change nothing."""


class SimPort(Protocol):
    """What the bus needs from a simulator."""

    def decode(self, what: str, payload: bytes, encoding: str | None) -> BaseModel:
        """The fault request for `sim/<what>`; raises `MachineError` (unknown key, bad payload)."""
        ...

    def apply(self, request: BaseModel) -> None:
        """Inject (or repair) the fault a decoded request asks for."""
        ...

    def world(self, stamp: float) -> BaseModel:
        """The simulated world as the `sim/world` reply reports it."""
        ...


Runner = Callable[[Request, Callable[[], BaseModel]], None]
"""Runs `make` where the simulator's world is (the daemon's scan thread, the supervisor's
plant thread) and answers the request with what it makes, from a thread that may wait on the
asker's link (never the scan thread: service/bus/outbox.py)."""


@dataclass
class Injection:
    """The `sim/**` route: shared by the daemon's bus and the supervisor's."""

    base: str
    port: SimPort | None
    backend: str
    """Named by the NOT_AVAILABLE answer when there is no simulator."""
    run: Runner
    wall: Callable[[], float]

    def routes(self) -> list[Route]:
        # Injection acts on the machine: `machine/*/sim/estop` must not press every E-stop.
        return [
            Route(
                "sim/**",
                self.inject,
                Wildcard.REFUSE,
                sniff=True,
                what="a simulator key",
                example="sim/<fault>",
            )
        ]

    def inject(self, request: Request) -> None:
        what = request.key[len(f"{self.base}/sim/") :]
        port = self.port
        if port is None:
            raise NotAvailable(
                f"sim/{what}: this machine runs the {self.backend} HAL, not the simulator"
            )
        if what == WORLD:  # read where faults are applied: never beside a change
            self.run(request, lambda: port.world(self.wall()))
            return
        fault = port.decode(what, request.payload, request.encoding)

        def apply() -> BaseModel:
            port.apply(fault)
            return port.world(self.wall())

        self.run(request, apply)
