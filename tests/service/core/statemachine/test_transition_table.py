"""The transition table runs: each trigger has one row per state, a row with several targets
names how it picks one, and a state change the table does not have is refused at run time."""

from __future__ import annotations

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.status import MachineState
from ride_machine.service.core.statemachine import TABLE, IllegalTransition, Occurrence
from ride_machine.service.core.statemachine.guards import PICKS
from ride_machine.service.core.statemachine.table import Pick
from tests.rig import rig_in

S = MachineState
C = Command


def test_each_trigger_has_one_row_per_state_and_a_pick_where_it_has_several_targets() -> None:
    seen: set[tuple[Command | Occurrence, MachineState]] = set()
    for rule in TABLE:
        assert (len(rule.targets) > 1) is (rule.pick is not None), rule
        for state in rule.sources:
            assert (rule.trigger, state) not in seen, (rule.trigger, state)
            seen.add((rule.trigger, state))


def test_a_state_change_the_table_does_not_have_is_refused_at_run_time() -> None:
    rig = rig_in(S.IDLE)
    transitions = len(rig.transitions)
    with pytest.raises(IllegalTransition, match="motion done: IDLE → RUNNING"):
        rig.state_machine.enter(
            Occurrence.MOTION_DONE, S.RUNNING, rig.clock(), "no such row in IDLE"
        )
    with pytest.raises(IllegalTransition, match="Stop: IDLE → RUNNING"):
        rig.state_machine.enter(C.STOP, S.RUNNING, rig.clock(), "Stop's row leads to DONE only")
    with pytest.raises(IllegalTransition, match="calibration saved: IDLE → None"):
        rig.state_machine.go(Occurrence.SAVED, rig.clock(), "no calibration is being saved")
    assert rig.state is S.IDLE
    assert len(rig.transitions) == transitions


def test_a_pick_outside_its_row_stops_the_cycle_with_the_state_unchanged(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The table chooses where Home's end leads (the rest state); a pick that chose another
    state is refused in the cycle it happens (the runner makes any exception a FAULT_HW)."""
    rig = rig_in(S.HOMING)
    monkeypatch.setitem(PICKS, Pick.REST, lambda facts: S.RUNNING)
    with pytest.raises(IllegalTransition, match="motion done: HOMING → RUNNING"):
        rig.run_to_state(S.IDLE)
    assert rig.state is S.HOMING
    assert (S.HOMING, S.RUNNING) not in {(t.old, t.new) for t in rig.transitions}
