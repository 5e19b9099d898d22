"""The gateway's pure parts: which events become OPC UA events, the machine views, the users
file, who may do what, and the units' OPC UA ids."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from asyncua import ua
from asyncua.crypto.permission_rules import UserRole

from ride_machine.rider.gateway.alarms import Severity, alarm_of
from ride_machine.rider.gateway.cli import build_parser, options_from
from ride_machine.rider.gateway.model import MachineView
from ride_machine.rider.gateway.security import OPERATOR, BadUsers, Caller, Rules, Users, read_users
from ride_machine.rider.gateway.supervision import Supervisor
from ride_machine.rider.gateway.variables import DEGREE, SECOND
from ride_machine.schema.events import Event
from ride_machine.schema.status import MachineState, Status

CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
READ = ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary)
ADD_NODES = ua.NodeId(ua.ObjectIds.AddNodesRequest_Encoding_DefaultBinary)
WRITE = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)


def _event(kind: str, **details: object) -> Event:
    return Event(seq=1, time=1.0, machine_id="m1", kind=kind, details={"kind": kind, **details})


def test_faults_estops_and_sessions_become_events_with_a_severity() -> None:
    fault = alarm_of(_event("fault_raised", code="TILT_TIMEOUT", message="tilt stuck"))
    assert fault is not None and fault.severity is Severity.HIGH and fault.code == "TILT_TIMEOUT"
    estop = alarm_of(_event("estop_pressed", state="FAULT_ESTOP"))
    assert estop is not None and estop.severity is Severity.URGENT
    ended = {
        "name": "s",
        "steps": 2,
        "steps_done": 1,
        "revolutions_done": 0,
        "revolutions_total": 3,
        "duration_s": 1.0,
    }
    done = alarm_of(_event("session_ended", outcome="DONE", **ended))
    stopped = alarm_of(_event("session_ended", outcome="STOPPED", **ended))
    assert done is not None and stopped is not None and done.severity < stopped.severity
    assert alarm_of(_event("command", command="Home", accepted=True, code="RESP_X")) is None
    assert alarm_of(_event("estop_latched")) is None


def _status(seq: int, state: MachineState = MachineState.IDLE, **more: object) -> Status:
    return Status(machine_id="m1", state=state, seq=seq, cycle=seq, time=float(seq), **more)


def test_a_late_status_never_replaces_a_newer_one_but_a_restart_does() -> None:
    view = MachineView("m1")
    view.apply(_status(5, MachineState.RUNNING))
    view.apply(_status(4, MachineState.IDLE))
    assert view.status is not None and view.status.state is MachineState.RUNNING
    view.apply(_status(1, MachineState.WARNING_NOT_HOME))  # the daemon restarted
    assert view.status.state is MachineState.WARNING_NOT_HOME


def test_a_status_read_on_attach_never_replaces_the_publication_that_overtook_it() -> None:
    """The gateway reads a machine's status as it attaches; an E-stop pressed meanwhile is
    published (seq 2) before the read's reply (seq 1) arrives. The E-stop stays (the CI run of
    stop 62 found the `Estop` condition inactive: the late read had been taken as a restart)."""
    view = MachineView("m1")
    view.apply(_status(2, MachineState.FAULT_ESTOP))
    view.apply(_status(1, MachineState.IDLE), snapshot=True)
    assert view.status is not None and view.status.state is MachineState.FAULT_ESTOP


def test_a_machine_back_after_its_token_went_is_read_again_whatever_its_seq() -> None:
    """A daemon restarted begins its `seq` again: once its token went and came back, the read
    of its status (seq 7 of the new run against 900 of the old) is taken."""
    view = MachineView("m1")
    view.apply(_status(900, MachineState.RUNNING))
    view.presence(False, 10.0)
    view.presence(True, 12.0)
    view.apply(_status(7, MachineState.WARNING_NOT_HOME), snapshot=True)
    assert view.status is not None and view.status.state is MachineState.WARNING_NOT_HOME
    view.apply(_status(6, MachineState.IDLE), snapshot=True)  # an older read of the new run
    assert view.status.state is MachineState.WARNING_NOT_HOME


def test_commands_are_counted_by_code_and_storage_warnings_by_prefix() -> None:
    view = MachineView("m1")
    for code, repeat in (
        ("RESP_HOME_ACCEPTED", False),
        ("WRONG_STATE", False),
        ("WRONG_STATE", False),
        ("WRONG_STATE", True),
    ):
        view.count(_event("command", command="Home", accepted=False, code=code, repeat=repeat))
    assert view.commands == {"RESP_HOME_ACCEPTED": 1, "WRONG_STATE": 2}
    view.apply(_status(2, warnings=["STORAGE_FAILED: calibration", "other"]))
    assert view.storage_warnings == 1


def test_the_users_file_names_the_bad_line(tmp_path: Path) -> None:
    good = tmp_path / "users"
    good.write_text("# operators\noperator:s3cr:et\n\nalice:pw\n")
    assert read_users(good) == {"operator": "s3cr:et", "alice": "pw"}
    bad = tmp_path / "bad"
    bad.write_text("operator\n")
    with pytest.raises(BadUsers, match=r"bad:1: expected user:password"):
        read_users(bad)
    with pytest.raises(BadUsers, match="cannot read"):
        read_users(tmp_path / "missing")


def test_a_password_makes_an_operator_none_is_anonymous_a_wrong_one_nobody() -> None:
    users = Users({"operator": "pw"}, {b"DER": "CN=op"})
    op = users.get_user(None, "operator", "pw")
    assert op is not None and op.role is OPERATOR and op.name == "operator"
    assert users.get_user(None, "operator", "nope") is None
    assert users.get_user(None, "ghost", "pw") is None
    anon = users.get_user(None)
    assert anon is not None and anon.role is UserRole.Anonymous
    cert = users.get_user(None, certificate=b"DER")
    assert cert is not None and cert.role is OPERATOR
    other = users.get_user(None, certificate=b"OTHER")
    assert other is not None and other.role is UserRole.Anonymous


@pytest.mark.hazard("H52")
def test_every_session_reads_and_calls_nobody_writes_or_edits_the_space() -> None:
    """The service-level rules; which method a session may call is the Call service's to say
    (tests/gateway/test_calls.py)."""
    rules = Rules()
    anon, op = Caller(role=UserRole.Anonymous), Caller(role=OPERATOR)
    for who in (anon, op):
        assert rules.check_validity(who, READ, None) and rules.check_validity(who, CALL, None)
        assert not rules.check_validity(who, WRITE, None)
        assert not rules.check_validity(who, ADD_NODES, None)


@pytest.mark.hazard("H53")
def test_a_supervising_session_ends_when_closed_or_silent_past_the_timeout() -> None:
    now = [100.0]
    open_keys: set[str] = set()
    sup = Supervisor(lambda key, operator: _Handle(), lambda: open_keys, 2.0, clock=lambda: now[0])
    a, b = Caller(role=OPERATOR, last_active=100.0), Caller(role=OPERATOR, last_active=100.0)
    open_keys |= {a.key, b.key}
    asyncio.run(sup.rider_for(a))
    asyncio.run(sup.rider_for(b))
    assert sup.gone() == []
    open_keys.discard(a.key)  # closed
    assert sup.gone() == [a.key]
    now[0] = 102.5  # b silent for 2.5 s
    assert sorted(sup.gone()) == sorted([a.key, b.key])


class _Handle:
    def close(self) -> None:
        return None


def test_units_carry_their_unece_codes() -> None:
    assert DEGREE.unit_id == (ord("D") << 8) | ord("D") == 17476
    assert SECOND.unit_id == 5457219  # "SEC"


def test_operators_without_the_gateways_certificate_are_a_usage_error(tmp_path: Path) -> None:
    users = tmp_path / "users"
    users.write_text("operator:pw\n")
    args = build_parser().parse_args(["--users", str(users)])
    with pytest.raises(BadUsers, match="need --certificate"):
        options_from(args, [], None, 1)
