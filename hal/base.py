"""The `Hal` protocol: one process-image read and one write per cycle, and a safe state."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from ride_machine.schema.findings import Finding


@dataclass(frozen=True, slots=True)
class Inputs:
    """The input half of the process image, keyed by channel name."""

    di: Mapping[str, bool]
    ai: Mapping[str, int]


@dataclass(slots=True)
class Outputs:
    """The output half of the process image (relay outputs), keyed by channel name."""

    ro: dict[str, bool] = field(default_factory=dict)
    pump: bool | None = None
    """The charge-pump output's level this cycle (None: the ride has none, or nothing drives
    it). It is no relay of the ride: `any_on` and a supervisor's `energised` leave it out."""

    def any_on(self) -> bool:
        return any(self.ro.values())


class HalError(Exception):
    """The IO backend failed (device gone, image unreadable); the loop goes safe on it."""


class HalConfigError(HalError):
    """The backend cannot run with this configuration; `findings` say what and where.

    `machine run` and `machine supervise` print the findings and exit with code 2.
    """

    def __init__(self, findings: list[Finding]) -> None:
        self.findings = findings
        super().__init__("; ".join(f"{f.path}: {f.message}" for f in findings))


@runtime_checkable
class Hal(Protocol):
    """A process image: inputs are scanned once per cycle, outputs written once per cycle."""

    def scan_inputs(self) -> Inputs:
        """Read the whole input image once."""
        ...

    def scan_outputs(self, outputs: Outputs) -> None:
        """Write the whole output image once."""
        ...

    def force_all_outputs_safe(self) -> None:
        """Drop every output to its safe state now; must work even after the loop failed."""
        ...

    def read_estop(self) -> bool:
        """True when the E-stop is active (read directly, for watchdogs and supervisors)."""
        ...

    def close(self) -> None:
        """Leave outputs safe and release the device."""
        ...
