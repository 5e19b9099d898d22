"""Two sessions hold one machine id: the state machine stops and refuses until it is alone."""

from __future__ import annotations

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import FaultCode
from ride_machine.schema.status import MachineState as S
from tests.rig import Rig


def _running() -> Rig:
    rig = Rig().ready()
    assert rig.send(Command.START).success
    rig.step(5)
    assert rig.relays_on()
    return rig


@pytest.mark.hazard("H35")
def test_meeting_a_second_holder_stops_motion_in_the_same_cycle() -> None:
    rig = _running()
    rig.state_machine.duplicate_id(("other",), "me", rig.clock())
    rig.step()
    assert rig.state is S.FAULT_HW
    assert (
        rig.state_machine.fault is not None
        and rig.state_machine.fault.code is FaultCode.DUPLICATE_ID
    )
    assert "other" in rig.state_machine.fault.message and "me" in rig.state_machine.fault.message
    assert not rig.relays_on()


def test_commands_are_refused_while_duplicated_and_checks_answered() -> None:
    rig = Rig().ready()
    rig.state_machine.duplicate_id(("other",), "me", rig.clock())
    for command in (Command.HOME, Command.START, Command.STOP, Command.CALIBRATE_TILT):
        reply = rig.send(command)
        assert reply.error is not None and reply.error.code is ErrorCode.DUPLICATE_ID, reply
    assert rig.send(Command.CHECK_HOME).success
    rig.step(100)
    assert not rig.relays_on()


@pytest.mark.hazard("H35")
def test_alone_again_commands_are_taken_and_nothing_moves_by_itself() -> None:
    rig = _running()
    rig.state_machine.duplicate_id(("other",), "me", rig.clock())
    rig.step()
    rig.state_machine.duplicate_id((), "me", rig.clock())
    rig.step(200)
    assert rig.state is S.FAULT_HW and not rig.relays_on()
    assert rig.state_machine.fault is not None and "alone again" in rig.state_machine.fault.message
    assert rig.send(Command.HOME).success
    rig.run_to_state(S.IDLE, max_s=30)
