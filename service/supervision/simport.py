"""A HAL backend's simulator (`hal.backends.Simulator`) as the bus's `SimPort`.

The simulator knows no daemon: it says a refusal as the codec does (`DecodeError`, carrying
the wire `Error`), and the bus answers `MachineError`s. Here one becomes the other, the wire
`Error` unchanged, for the daemon's simulator HAL and the supervisor's world alike.
"""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel

from ride_machine.hal.backends import Simulator
from ride_machine.schema.codec import DecodeError
from ride_machine.service.bus.injection import SimPort
from ride_machine.service.errors import Rejected


@dataclass(frozen=True)
class SimFaults:
    """`sim/<fault>` requests into `sim`, refusals as `Rejected`."""

    sim: Simulator

    def decode(self, what: str, payload: bytes, encoding: str | None) -> BaseModel:
        try:
            return self.sim.decode(what, payload, encoding)
        except DecodeError as exc:
            raise Rejected(exc.error) from None

    def apply(self, request: BaseModel) -> None:
        self.sim.apply(request)

    def world(self, stamp: float) -> BaseModel:
        return self.sim.world(stamp)


def sim_port(sim: Simulator | None) -> SimPort | None:
    """`sim` for the bus; None (every `sim/*` key answers NOT_AVAILABLE) without a simulator."""
    return None if sim is None else SimFaults(sim)
