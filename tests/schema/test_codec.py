"""The wire codec: round trips of every model, format sniffing, and precise decode errors."""

from __future__ import annotations

import importlib
import inspect
import json
import pkgutil

import msgpack
import pytest
from pydantic import BaseModel

from ride_machine import schema
from ride_machine.schema import sim
from ride_machine.schema.axes import AxisRecord, PnStatus
from ride_machine.schema.base import OpenWireModel, WireModel
from ride_machine.schema.calibration import (
    CalibrationRecord,
    CalibrationSet,
    CalibrationSource,
    RotateCalibrationSet,
    RotateCalibrationValues,
    TiltCalibrationSet,
    TiltCalibrationValues,
)
from ride_machine.schema.codec import (
    Format,
    decode,
    encode,
    sniff_format,
)
from ride_machine.schema.commands import (
    DEFAULT_SESSION,
    CheckResult,
    CommandRequest,
    Direction,
    Reply,
    ReplyCode,
    RotateStep,
    Session,
    StartRequest,
    TiltStep,
)
from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.diag import CycleDiag, TimingStats
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.schema.findings import Finding, Findings, Severity
from ride_machine.schema.io import IoKind, IoValue
from ride_machine.schema.params import ParamSet, ParamValue
from ride_machine.schema.status import (
    AxesFlags,
    EstopInfo,
    Fault,
    FaultCode,
    MachineState,
    MotionRef,
    SessionProgress,
    Status,
)
from tests.schema.event_samples import EVENT_SAMPLES

MIXED = Session(
    name="mixed",
    steps=[
        TiltStep(degrees=30.5),
        RotateStep(direction=Direction.CCW, revolutions=2),
        TiltStep(degrees=0),
    ],
)
ERROR = Error(code=ErrorCode.WRONG_STATE, message="Start is not accepted in RUNNING", path="")
FAULT = Fault(code=FaultCode.ROTATE_HOME_TIMEOUT, message="not seen within 8 s", axis="rotate")
PROGRESS = SessionProgress(
    name="default",
    step_index=1,
    step_count=2,
    step_kind="rotate",
    revolutions_done=2,
    revolutions_total=3,
    tilt_target_deg=45.0,
)
TIMING = TimingStats(last=1e-4, mean=2e-4, min=5e-5, max=1e-3, p50=1.9e-4, p99=9e-4)
IO = IoValue(name="tiltPosition", kind=IoKind.AI, channel="InputValue_1", value=2994, time=12.5)
PARAM = ParamValue(name="tilt.tolerance_deg", value=1.0, default=1.0, persisted=False, unit="°")

SAMPLES: list[BaseModel] = [
    TiltStep(degrees=45.0),
    RotateStep(direction=Direction.CW, revolutions=3),
    DEFAULT_SESSION,
    MIXED,
    CommandRequest(transaction_id="t-1"),
    CommandRequest(transaction_id="a.b:c@d/e+f-1", timecode=1700000000.25, rider="rider-7"),
    StartRequest(transaction_id="s1"),
    StartRequest(transaction_id="s2", session=MIXED, timecode=3.0),
    CheckResult(ok=False, tilt=True, rotate=False),
    MotionRef(transaction_id="h1", command="Home", started_at=5.0),
    CalibrationRecord(
        machine_id="m1",
        tilt=TiltCalibrationValues(
            offset_counts=1194.0,
            gain_counts_per_deg=40.0,
            source=CalibrationSource.MANUAL,
            at=7.5,
        ),
        rotate=RotateCalibrationValues(revolution_s=4.0, home_arc_deg=9.9, speed_dps=90.0),
        complete=True,
        time=8.0,
    ),
    TiltCalibrationValues(offset_counts=1.0, gain_counts_per_deg=2.0),
    RotateCalibrationValues(revolution_s=4.0, home_arc_deg=9.9, speed_dps=90.0, at=1.0),
    TiltCalibrationSet(offset_counts=-3.5, gain_counts_per_deg=2.0),
    RotateCalibrationSet(revolution_s=4.0, home_arc_deg=9.9),
    CalibrationSet(
        transaction_id="cal-1",
        timecode=3.0,
        tilt=TiltCalibrationSet(offset_counts=1194.0, gain_counts_per_deg=40.0),
        rotate=RotateCalibrationSet(revolution_s=4.0, home_arc_deg=9.9),
    ),
    Completion(
        machine_id="m1",
        transaction_id="a.b/c",
        command="Start",
        outcome=Outcome.REFUSED,
        code="NOT_HOME",
        reason="Start refused: tilt not home",
        state=MachineState.WARNING_NOT_HOME,
        rider="r1",
        started_at=5.0,
        time=5.0,
    ),
    Reply(
        transaction_id="t1",
        command="Start",
        timecode=10.0,
        success=True,
        code=ReplyCode.RESP_START_ACCEPTED,
        state=MachineState.RUNNING,
    ),
    Reply(
        transaction_id="t2",
        command="CheckHome",
        timecode=11.0,
        success=True,
        code=ReplyCode.RESP_CHECK,
        state=MachineState.IDLE,
        result=CheckResult(ok=True, tilt=True, rotate=True),
    ),
    Reply.failure(ERROR, transaction_id=None, command=None, timecode=0.0),
    ERROR,
    Error(code=ErrorCode.BAD_PAYLOAD, message="bad", path="/session/steps/0/degrees"),
    FAULT,
    PROGRESS,
    AxesFlags(tilt=True, rotate=False),
    EstopInfo(active=False, latched=True),
    Status(machine_id="m1", state=MachineState.IDLE, seq=1, cycle=1, time=0.0),
    Status(
        machine_id="m1",
        state=MachineState.FAULT_HW,
        previous_state=MachineState.RUNNING,
        session=PROGRESS,
        warnings=["calibration.json: corrupt"],
        fault=FAULT,
        estop=EstopInfo(active=True, latched=True),
        calibrated=AxesFlags(tilt=True, rotate=True),
        homed=AxesFlags(tilt=False, rotate=False),
        tilt_deg=44.6,
        rotate_deg=120.5,
        rider_connected=True,
        seq=99,
        cycle=12345,
        time=1700000000.5,
        uptime_s=123.45,
    ),
    AxisRecord(
        axis="rotate",
        axis_number=0,
        pn_status=int(PnStatus.MOVING | PnStatus.DRIVE_ENABLED),
        cycle=7,
        position_cmd=10.0,
        position_fb=9.5,
        velocity_cmd=90.0,
        velocity_fb=89.9,
        time=1.0,
    ),
    IO,
    IoValue(name="estop", kind=IoKind.DI, channel="I_3", value=True, time=1.0),
    TIMING,
    CycleDiag(
        period_s=0.01,
        cycles=100,
        execution=TIMING,
        jitter=TIMING,
        overruns=2,
        missed_cycles=3,
        commands=4,
        window=100,
        since=0.0,
        time=1.0,
    ),
    PARAM,
    ParamValue(name="machine.mode", value="fast", default="slow", persisted=True, changed_at=5.0),
    ParamSet(transaction_id="p1", value=2.5, persist=True),
    ParamSet(transaction_id="p2", reset=True),
    Finding(category="unknown_key", severity=Severity.ERROR, path="/loop/x", message="no"),
    Findings(
        ok=False,
        findings=[Finding(category="c", severity=Severity.WARNING, path="", message="m")],
    ),
    sim.SimEstop(pressed=True),
    sim.SimHomeSwitch(transaction_id="h", axis=sim.SimAxis.TILT, stuck=sim.SwitchState.CLOSED),
    sim.SimHomeSwitch(axis=sim.SimAxis.ROTATE),
    sim.SimTiltSignal(frozen=True, noise_counts=12.5),
    sim.SimStall(axis=sim.SimAxis.ROTATE, stalled=False),
    sim.SimStalls(probability=0.05, max_s=0.05),
    sim.SimPlace(tilt_deg=-5.0),
    sim.SimClear(),
    sim.SimWorldState(
        time=1.0,
        tilt_deg=2.0,
        rotate_deg=3.0,
        revolutions=0.5,
        estop_pressed=False,
        relays={"O_1": True},
        faults={"tilt_ai_frozen": False},
    ),
    *EVENT_SAMPLES,
]
IDS = [f"{type(m).__name__}-{i}" for i, m in enumerate(SAMPLES)]


def wire_models() -> set[type[BaseModel]]:
    """Every pydantic model defined in the `schema` package."""
    found: set[type[BaseModel]] = set()
    for info in pkgutil.iter_modules(schema.__path__):
        module = importlib.import_module(f"ride_machine.schema.{info.name}")
        for _, obj in inspect.getmembers(module, inspect.isclass):
            if (
                issubclass(obj, BaseModel)
                and obj.__module__ == module.__name__
                and obj not in (WireModel, OpenWireModel)
            ):
                found.add(obj)
    return found


def test_every_wire_model_has_a_round_trip_sample() -> None:
    missing = {m.__name__ for m in wire_models()} - {type(s).__name__ for s in SAMPLES}
    assert not missing, f"add samples for {sorted(missing)}"


@pytest.mark.parametrize("fmt", list(Format))
@pytest.mark.parametrize("model", SAMPLES, ids=IDS)
def test_round_trip(model: BaseModel, fmt: Format) -> None:
    data = encode(model, fmt)
    assert isinstance(data, bytes)
    back = decode(type(model), data, fmt)
    assert back == model
    assert encode(back, fmt) == data
    # The bytes are what they claim to be, and sniffing without an encoding finds the format.
    if fmt is Format.JSON:
        assert isinstance(json.loads(data), dict)
    else:
        assert isinstance(msgpack.unpackb(data), dict)
    assert sniff_format(data, None) is fmt


def test_enums_travel_as_their_string_values() -> None:
    status = Status(machine_id="m1", state=MachineState.RUNNING, seq=1, cycle=1, time=0.0)
    plain = msgpack.unpackb(encode(status))
    assert plain["state"] == "RUNNING"
    assert json.loads(encode(status, Format.JSON))["state"] == "RUNNING"
    reply = Reply.failure(ERROR, transaction_id="x", command="Start", timecode=1.0)
    assert msgpack.unpackb(encode(reply))["error"]["code"] == "WRONG_STATE"
