"""The wire models themselves: defaults, validation rules, enums and the command table."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from ride_machine.schema import SCHEMA_VERSION
from ride_machine.schema.axes import AXIS_RECORD_VERSION, AxisRecord, PnStatus
from ride_machine.schema.commands import (
    ALLOWED_STATES,
    DEFAULT_SESSION,
    READ_ONLY_COMMANDS,
    REQUEST_MODELS,
    REST_STATES,
    CheckResult,
    Command,
    CommandRequest,
    Direction,
    Reply,
    ReplyCode,
    RotateStep,
    Session,
    StartRequest,
    TiltStep,
)
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.schema.findings import Finding, Findings, Severity
from ride_machine.schema.params import ParamSet
from ride_machine.schema.status import (
    FAULT_STATES,
    MOTION_STATES,
    EstopInfo,
    FaultCode,
    MachineState,
    Status,
)

S = MachineState


def test_the_ten_states_of_the_design() -> None:
    assert [s.value for s in MachineState] == [
        "IDLE",
        "HOMING",
        "CALIBRATING",
        "RUNNING",
        "PAUSED",
        "DONE",
        "FAULT_ESTOP",
        "FAULT_HW",
        "WARNING_NEEDS_CALIBRATION",
        "WARNING_NOT_HOME",
    ]
    assert frozenset({S.HOMING, S.CALIBRATING, S.RUNNING}) == MOTION_STATES
    assert frozenset({S.FAULT_ESTOP, S.FAULT_HW}) == FAULT_STATES
    assert frozenset({S.IDLE, S.DONE, S.WARNING_NEEDS_CALIBRATION, S.WARNING_NOT_HOME}) == (
        REST_STATES
    )
    assert not (MOTION_STATES & FAULT_STATES)
    assert not (MOTION_STATES & REST_STATES)


def test_the_nine_commands_and_their_keys() -> None:
    keys = {c: c.key for c in Command}
    assert keys == {
        Command.CALIBRATE_TILT: "calibrate/tilt",
        Command.CALIBRATE_ROTATE: "calibrate/rotate",
        Command.HOME: "home",
        Command.START: "start",
        Command.PAUSE: "pause",
        Command.RESUME: "resume",
        Command.STOP: "stop",
        Command.CHECK_CALIBRATION: "check/calibration",
        Command.CHECK_HOME: "check/home",
    }
    assert all(Command.from_key(k) is c for c, k in keys.items())
    assert Command.from_key("launch") is None
    assert Command.from_key("Home") is None  # keys, not names


def test_command_table_is_complete_and_consistent() -> None:
    assert set(ALLOWED_STATES) == set(Command)
    assert set(REQUEST_MODELS) == set(Command)
    assert REQUEST_MODELS[Command.START] is StartRequest
    assert all(REQUEST_MODELS[c] is CommandRequest for c in Command if c is not Command.START)
    for command in READ_ONLY_COMMANDS:
        assert ALLOWED_STATES[command] == frozenset(MachineState)
    assert ALLOWED_STATES[Command.STOP] == frozenset(MachineState)
    assert ALLOWED_STATES[Command.PAUSE] == MOTION_STATES
    # Nothing that moves the machine is accepted while it is already moving.
    for command in (Command.START, Command.HOME, Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE):
        assert not (ALLOWED_STATES[command] & MOTION_STATES)


def test_default_session_is_tilt_45_then_three_cw_revolutions() -> None:
    assert DEFAULT_SESSION.steps == [
        TiltStep(degrees=45.0),
        RotateStep(direction=Direction.CW, revolutions=3),
    ]
    assert DEFAULT_SESSION.name == "default"


def test_step_defaults_and_discriminator() -> None:
    assert RotateStep().direction is Direction.CW
    assert RotateStep().revolutions == 1
    session = Session.model_validate(
        {"steps": [{"kind": "rotate"}, {"kind": "tilt", "degrees": 10}]}
    )
    assert isinstance(session.steps[0], RotateStep)
    assert isinstance(session.steps[1], TiltStep)
    assert session.steps[1].degrees == 10.0
    assert RotateStep.model_validate({"direction": "ccw"}).direction is Direction.CCW


@pytest.mark.parametrize(
    "raw",
    [
        {"steps": []},
        {"steps": [{"kind": "rotate"}] * 101},
        {"name": "", "steps": [{"kind": "rotate"}]},
        {"name": "n" * 65, "steps": [{"kind": "rotate"}]},
        {"steps": [{"kind": "rotate", "revolutions": 0}]},
        {"steps": [{"kind": "rotate", "revolutions": 1001}]},
        {"steps": [{"kind": "tilt", "degrees": float("nan")}]},
        {"steps": [{"kind": "tilt", "degrees": float("inf")}]},
        {"steps": [{"kind": "tilt", "degrees": "10"}]},
        {"steps": [{"kind": "swing"}]},
    ],
    ids=[
        "no-steps",
        "too-many-steps",
        "empty-name",
        "long-name",
        "zero-revolutions",
        "too-many-revolutions",
        "nan-degrees",
        "inf-degrees",
        "string-degrees",
        "unknown-kind",
    ],
)
def test_invalid_sessions_are_refused(raw: dict[str, object]) -> None:
    with pytest.raises(ValidationError):
        Session.model_validate(raw)


def test_session_limits_are_inclusive() -> None:
    Session.model_validate({"name": "n" * 64, "steps": [{"kind": "rotate"}] * 100})
    Session.model_validate({"steps": [{"kind": "rotate", "revolutions": 1000}]})


@pytest.mark.parametrize(
    "tid", ["t", "a" * 64, "rider-1:2024-01-01T00:00:00.5+00", "x/y@z_", "0", "A.B"]
)
def test_transaction_id_accepts_plain_tokens(tid: str) -> None:
    assert CommandRequest(transaction_id=tid).transaction_id == tid


@pytest.mark.parametrize("tid", ["", "a" * 65, "with space", "tab\t", "ünicode", "semi;colon"])
def test_transaction_id_refuses_anything_else(tid: str) -> None:
    with pytest.raises(ValidationError):
        CommandRequest(transaction_id=tid)


def test_requests_are_strict_frozen_and_closed() -> None:
    with pytest.raises(ValidationError):
        CommandRequest.model_validate({"transaction_id": "t", "unknown": 1})
    with pytest.raises(ValidationError):
        CommandRequest.model_validate({"transaction_id": 7})
    request = CommandRequest(transaction_id="t")
    with pytest.raises(ValidationError):
        request.transaction_id = "u"  # type: ignore[misc]
    with pytest.raises(ValidationError):
        ParamSet.model_validate({"transaction_id": "t", "persist": "yes"})


def test_records_ignore_unknown_fields() -> None:
    status = Status.model_validate(
        {"machine_id": "m", "state": "IDLE", "seq": 1, "cycle": 1, "time": 0.0, "new": 1}
    )
    assert status.state is S.IDLE
    assert not hasattr(status, "new")


def test_status_defaults() -> None:
    status = Status(machine_id="m1", state=S.WARNING_NOT_HOME, seq=1, cycle=0, time=0.0)
    assert status.schema_version == SCHEMA_VERSION
    assert status.previous_state is None
    assert status.session is None
    assert status.warnings == []
    assert status.fault is None
    assert status.estop == EstopInfo(active=False, latched=False)
    assert status.homed.tilt is False
    assert status.homed.rotate is False
    assert status.calibrated.tilt is False


def test_reply_failure_carries_the_error_in_both_forms() -> None:
    error = Error(code=ErrorCode.NOT_HOME, message="Start refused: rotate not home")
    reply = Reply.failure(
        error, transaction_id="t", command="Start", timecode=5.0, state=S.WARNING_NOT_HOME
    )
    assert reply.success is False
    assert reply.code is ReplyCode.RESP_ERROR
    assert reply.error == error
    assert reply.error_message == error.message
    assert reply.state is S.WARNING_NOT_HOME
    assert reply.schema_version == SCHEMA_VERSION
    assert reply.result is None


def test_error_and_reply_codes_are_stable_strings() -> None:
    for enum in (ErrorCode, ReplyCode, FaultCode, MachineState):
        assert all(member.value == member.name for member in enum)
    assert {"WRONG_STATE", "ESTOP_ACTIVE", "NOT_CALIBRATED", "NOT_HOME", "INVALID_SESSION"} <= {
        c.value for c in ErrorCode
    }
    assert {"RESP_START_ACCEPTED", "RESP_PAUSED", "RESP_RESUMED", "RESP_DONE"} <= {
        c.value for c in ReplyCode
    }


def test_error_path_defaults_to_the_whole_request() -> None:
    assert Error(code=ErrorCode.BUSY, message="busy").path == ""


def test_check_result_fields() -> None:
    result = CheckResult(ok=False, tilt=True, rotate=False)
    assert result.model_dump() == {"ok": False, "tilt": True, "rotate": False}


def test_axis_record_status_bits() -> None:
    assert [int(b) for b in PnStatus] == [1, 2, 4, 8, 16]  # seed 002's four, then ours
    record = AxisRecord(
        axis="tilt",
        axis_number=1,
        pn_status=int(PnStatus.SETTLED | PnStatus.DRIVE_ENABLED),
        cycle=1,
        position_cmd=0.0,
        position_fb=0.0,
        velocity_cmd=0.0,
        velocity_fb=0.0,
        time=0.0,
    )
    assert record.version == AXIS_RECORD_VERSION
    assert PnStatus(record.pn_status) & PnStatus.SETTLED
    assert not PnStatus(record.pn_status) & PnStatus.MOVING


def test_findings_model() -> None:
    finding = Finding(category="unknown_key", severity="warning", path="/x", message="m")
    assert finding.severity is Severity.WARNING
    assert Findings(ok=True, findings=[finding]).findings[0] == finding
