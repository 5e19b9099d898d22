"""A machine's conditions as its statuses and its token move them (rider/gateway/conditions.py,
pure): which become active, which stay retained until acknowledged, what Acknowledge refuses."""

from __future__ import annotations

import pytest

from ride_machine.rider.gateway.conditions import AckRefused, MachineConditions
from ride_machine.schema.status import EstopInfo, Fault, FaultCode, MachineState, Status


def _status(seq: int, state: MachineState = MachineState.IDLE, **more: object) -> Status:
    return Status(machine_id="m1", state=state, seq=seq, cycle=seq, time=float(seq), **more)


def _names(changed: list) -> set[str]:  # type: ignore[type-arg]
    return {c.name for c in changed}


def test_an_estop_raises_estop_and_faulted_and_stays_retained_until_acknowledged() -> None:
    m = MachineConditions("m1")
    assert m.observe(_status(1)) == []  # a quiet machine: nothing to list
    pressed = _status(2, MachineState.FAULT_ESTOP, estop=EstopInfo(active=True, latched=True))
    assert _names(m.observe(pressed)) == {"Estop", "Faulted"}
    estop = m.by_name["Estop"]
    assert (estop.active, estop.acked, estop.retain, estop.time) == (True, False, True, 2.0)
    assert m.observe(pressed) == []  # the same status again (a heartbeat): no new event
    released = _status(3, MachineState.FAULT_ESTOP, estop=EstopInfo(latched=True))
    assert _names(m.observe(released)) == {"Estop"}  # the message says it, still active
    assert "latched" in estop.message and estop.active
    m.observe(_status(4, MachineState.DONE))
    assert (estop.active, estop.retain) == (False, True)  # inactive, never acknowledged
    first = estop.event_id
    estop.acknowledge(first, "seen", "operator", 5.0)
    assert (estop.acked, estop.retain, estop.user, estop.comment) == (
        True,
        False,
        "operator",
        "seen",
    )
    assert estop.event_id != first  # the acknowledgement is an event of its own
    assert [c.name for c in m.retained()] == ["Faulted"]


def test_acknowledge_needs_the_latest_event_and_an_unacknowledged_state() -> None:
    m = MachineConditions("m1")
    (lost,) = m.presence(False, 1.0)
    old = lost.event_id
    m.presence(True, 2.0)
    with pytest.raises(AckRefused) as stale:
        lost.acknowledge(old, "", "operator", 3.0)
    assert stale.value.reason == "BadEventIdUnknown"
    lost.acknowledge(lost.event_id, "", "operator", 3.0)
    with pytest.raises(AckRefused) as twice:
        lost.acknowledge(lost.event_id, "", "operator", 4.0)
    assert twice.value.reason == "BadConditionBranchAlreadyAcked"
    (again,) = m.presence(False, 5.0)  # lost again: a new alarm, unacknowledged
    assert (again.active, again.acked, again.comment, again.user) == (True, False, "", "")


def test_each_fault_code_is_a_condition_of_its_own() -> None:
    m = MachineConditions("m1")
    tilt = Fault(code=FaultCode.TILT_TIMEOUT, message="tilt stuck")
    assert _names(m.observe(_status(1, MachineState.FAULT_HW, fault=tilt))) == {
        "Faulted",
        "Fault.TILT_TIMEOUT",
    }
    rotate = Fault(code=FaultCode.ROTATE_HOME_TIMEOUT, message="no home edge")
    changed = m.observe(_status(2, MachineState.FAULT_HW, fault=rotate))
    assert _names(changed) == {"Faulted", "Fault.TILT_TIMEOUT", "Fault.ROTATE_HOME_TIMEOUT"}
    assert not m.by_name["Fault.TILT_TIMEOUT"].active
    assert (
        m.by_name["Fault.ROTATE_HOME_TIMEOUT"].message == "fault ROTATE_HOME_TIMEOUT: no home edge"
    )
    estop = Fault(code=FaultCode.ESTOP, message="E-stop")
    m.observe(_status(3, MachineState.FAULT_ESTOP, fault=estop))
    assert "Fault.ESTOP" not in m.by_name  # the E-stop has its own condition
