"""What a Rider reads from its machine (status, IO, axes, diagnostics, calibration, parameters,
the simulator's world) and the settings it writes there (calibration by hand, parameters)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import (
    CalibrationRecord,
    CalibrationSet,
    RotateCalibrationSet,
    TiltCalibrationSet,
)
from ride_machine.schema.codec import encode, pack
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.findings import Findings
from ride_machine.schema.io import IoValue
from ride_machine.schema.params import ParamSet, ParamValue
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import Status

from .commands import Commands
from .machines import Machines
from .transport import Transport


@dataclass
class Reads:
    """Reads and settings on this Rider's machine."""

    machines: Machines
    transport: Transport
    commands: Commands

    def status(self, timeout: float | None = None) -> Status:
        return self.transport.get_one(f"{self.machines.base}/status", None, Status, timeout)

    def io(self) -> list[IoValue]:
        points = self.transport.get_all(f"{self.machines.base}/io/**", IoValue)
        return sorted(points, key=lambda p: (p.kind, p.name))

    def axes(self) -> list[AxisRecord]:
        records = self.transport.get_all(f"{self.machines.base}/axis/**", AxisRecord)
        return sorted(records, key=lambda a: a.axis)

    def diag(self, reset: bool = False) -> CycleDiag:
        """The scan loop's diagnostics; `reset` also clears min/max, overruns and missed
        cycles (a command key, `diag/reset`, so the ACL can keep it from read-only identities)."""
        base = self.machines.base
        key = f"{base}/diag/reset" if reset else f"{base}/diag/cycle"
        return self.transport.get_one(key, None, CycleDiag, None)

    def validate(self, candidate: bytes | None = None) -> Findings:
        """Findings for the running config, or for a candidate TOML/JSON config."""
        key = f"{self.machines.base}/config/validate"
        return self.transport.get_one(key, candidate, Findings, None)

    def calibration(self) -> CalibrationRecord:
        """The machine's calibration values: how and when each axis got them."""
        key = f"{self.machines.base}/calibration"
        return self.transport.get_one(key, None, CalibrationRecord, None)

    def set_calibration(
        self, tilt: TiltCalibrationSet | None, rotate: RotateCalibrationSet | None
    ) -> CalibrationRecord:
        """Enter calibration values by hand (`Rider.set_calibration`)."""
        req = CalibrationSet(
            transaction_id=self.commands.new_transaction_id(),
            timecode=time.time(),
            tilt=tilt,
            rotate=rotate,
        )
        key = f"{self.machines.base}/calibration/set"
        timeout = max(self.transport.link.timeout, 6.0)
        return self.transport.get_one(key, encode(req), CalibrationRecord, timeout)

    def params(self) -> list[ParamValue]:
        values = self.transport.get_all(f"{self.machines.base}/params/**", ParamValue)
        return sorted(values, key=lambda p: p.name)

    def param(self, name: str) -> ParamValue:
        return self.transport.get_one(f"{self.machines.base}/params/{name}", None, ParamValue, None)

    def set_param(self, name: str, value: Any, *, persist: bool = False) -> ParamValue:
        req = ParamSet.model_validate(
            {
                "transaction_id": self.commands.new_transaction_id(),
                "value": value,
                "persist": persist,
            }
        )
        return self._set_param(name, req)

    def reset_param(self, name: str) -> ParamValue:
        req = ParamSet(transaction_id=self.commands.new_transaction_id(), reset=True)
        return self._set_param(name, req)

    def _set_param(self, name: str, req: ParamSet) -> ParamValue:
        key = f"{self.machines.base}/params/{name}"
        return self.transport.get_one(key, encode(req), ParamValue, None)

    def sim(self, fault: str, **payload: Any) -> SimWorldState:
        """Inject a simulator fault (estop, home, tilt_ai, stall, clear) or read the `world`."""
        body = None if fault == "world" else pack(payload)
        return self.transport.get_one(
            f"{self.machines.base}/sim/{fault}", body, SimWorldState, None
        )
