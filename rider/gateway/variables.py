"""The OPC UA variables of a machine, as data: name, type, unit, and where each value comes from.

Pure: each extractor reads a wire model and returns the value (None: unknown, written as a Bad
quality). rider/gateway/space.py turns these tables into nodes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from asyncua import ua

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.io import IoKind, IoValue
from ride_machine.schema.status import Status

V = ua.VariantType


@dataclass(frozen=True)
class Unit:
    """A UNECE Rec. 20 unit, as OPC UA's EUInformation names it (Part 8, 5.6.3)."""

    code: str
    symbol: str
    description: str

    @property
    def unit_id(self) -> int:
        """The code's characters packed into an integer, as Part 8 defines UnitId."""
        value = 0
        for char in self.code:
            value = (value << 8) | ord(char)
        return value


DEGREE = Unit("DD", "°", "degree (angle)")
DEGREE_PER_SECOND = Unit("E96", "°/s", "degree per second")
SECOND = Unit("SEC", "s", "second")
UNITS_URI = "http://www.opcfoundation.org/UA/units/un/cefact"

TILT_RANGE = (-90.0, 120.0)
"""The tilt angles a machine's configuration may allow (tilt.min_deg, tilt.max_deg bounds), °."""
ROTATE_RANGE = (0.0, 360.0)
SPEED_RANGES = {"tilt": (-360.0, 360.0), "rotate": (-3600.0, 3600.0)}
"""The speeds a configuration may set (nominal_speed_dps bounds), °/s, either way."""
POSITION_RANGES = {"tilt": TILT_RANGE, "rotate": ROTATE_RANGE}


@dataclass(frozen=True)
class Var:
    """One variable: its browse name, type, unit (if any), and its value from a model. With a
    `eurange` it is an `AnalogItemType` (a PercentDeadband is taken on it); with a unit only,
    an `AnalogUnitType`; else a `BaseDataVariableType`."""

    name: str
    vtype: ua.VariantType
    read: Callable[[Any], Any]
    unit: Unit | None = None
    doc: str = ""
    eurange: tuple[float, float] | None = None


def _fault_code(s: Status) -> str:
    return str(s.fault.code) if s.fault else ""


def _session(s: Status, attr: str) -> Any:
    return getattr(s.session, attr) if s.session is not None else 0


STATUS_VARS: tuple[Var, ...] = (
    Var("State", V.String, lambda s: str(s.state), doc="the machine's state, e.g. RUNNING"),
    Var("PreviousState", V.String, lambda s: str(s.previous_state or "")),
    Var("FaultCode", V.String, _fault_code, doc="empty when no fault is active"),
    Var("FaultReason", V.String, lambda s: s.fault.message if s.fault else ""),
    Var("EstopActive", V.Boolean, lambda s: s.estop.active),
    Var("EstopLatched", V.Boolean, lambda s: s.estop.latched),
    Var("TiltCalibrated", V.Boolean, lambda s: s.calibrated.tilt),
    Var("RotateCalibrated", V.Boolean, lambda s: s.calibrated.rotate),
    Var("TiltHomed", V.Boolean, lambda s: s.homed.tilt),
    Var("RotateHomed", V.Boolean, lambda s: s.homed.rotate),
    Var("RiderConnected", V.Boolean, lambda s: s.rider_connected),
    Var("TiltPosition", V.Double, lambda s: s.tilt_deg, DEGREE, eurange=TILT_RANGE),
    Var("RotatePosition", V.Double, lambda s: s.rotate_deg, DEGREE, eurange=ROTATE_RANGE),
    Var("SessionName", V.String, lambda s: s.session.name if s.session else ""),
    Var("SessionStep", V.Int32, lambda s: _session(s, "step_index")),
    Var("SessionSteps", V.Int32, lambda s: _session(s, "step_count")),
    Var("RevolutionsDone", V.Int32, lambda s: _session(s, "revolutions_done")),
    Var("RevolutionsTotal", V.Int32, lambda s: _session(s, "revolutions_total")),
    Var("Motion", V.String, lambda s: s.motion.command if s.motion else ""),
    Var("Warnings", V.String, lambda s: "; ".join(s.warnings)),
    Var("Uptime", V.Double, lambda s: s.uptime_s, SECOND),
    Var("StatusSeq", V.UInt64, lambda s: s.seq, doc="grows with every status publication"),
)
"""Under the machine's object, from `machine/<id>/status`."""

DIAG_VARS: tuple[Var, ...] = (
    Var("Period", V.Double, lambda d: d.period_s, SECOND),
    Var("CycleTimeP50", V.Double, lambda d: d.execution.p50, SECOND),
    Var("CycleTimeP99", V.Double, lambda d: d.execution.p99, SECOND),
    Var("CycleTimeMax", V.Double, lambda d: d.execution.max, SECOND),
    Var("JitterP99", V.Double, lambda d: d.jitter.p99, SECOND),
    Var("Cycles", V.UInt64, lambda d: d.cycles),
    Var("Overruns", V.UInt64, lambda d: d.overruns),
    Var("MissedCycles", V.UInt64, lambda d: d.missed_cycles),
)
"""Under `Diagnostics`, from `machine/<id>/diag/cycle`."""

AXES = ("tilt", "rotate")
"""The axes a machine publishes (`axis/<name>`)."""


def axis_vars(axis: str) -> tuple[Var, ...]:
    """Under `Axes/<axis>`, from `machine/<id>/axis/<axis>` (the ranges are the axis')."""
    where = POSITION_RANGES.get(axis, (-3600.0, 3600.0))  # another axis: the widest
    speed = SPEED_RANGES.get(axis, SPEED_RANGES["rotate"])
    return (
        Var(
            "PositionFeedback",
            V.Double,
            lambda a: a.position_fb if a.position_known else None,
            DEGREE,
            eurange=where,
        ),
        Var("PositionCommanded", V.Double, lambda a: a.position_cmd, DEGREE, eurange=where),
        Var("Velocity", V.Double, lambda a: a.velocity_fb, DEGREE_PER_SECOND, eurange=speed),
        Var("Moving", V.Boolean, lambda a: bool(a.pn_status & 0b10)),
        Var("StatusBits", V.UInt32, lambda a: a.pn_status, doc="FastData pn_status bits"),
    )


def io_var(value: IoValue) -> Var:
    """A DI or RO is a Boolean, an AI its raw counts."""
    if value.kind is IoKind.AI:
        return Var(value.name, V.Int32, lambda v: int(v.value))
    return Var(value.name, V.Boolean, lambda v: bool(v.value))


def source_time(update: Status | CycleDiag | IoValue | AxisRecord) -> float:
    """The machine's own time of a publication (seconds since the epoch)."""
    return update.time
