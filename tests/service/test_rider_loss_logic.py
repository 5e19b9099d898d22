"""The rider-loss policy in the state machine: pause, stop, ignore, and the grace period."""

from __future__ import annotations

import pytest

from schema.commands import Command
from schema.status import MachineState as S
from service.config import MachineConfig
from tests.rig import Rig


def _running(policy: str, grace_s: float = 0.0) -> Rig:
    cfg = MachineConfig().with_overrides(rider_loss={"policy": policy, "grace_s": grace_s})
    rig = Rig(cfg).ready()
    assert rig.send(Command.START, rider="r1").success
    rig.step(5)
    assert rig.relays_on()
    assert rig.control.rider_connected
    return rig


@pytest.mark.parametrize(
    ("policy", "state"), [("pause", S.PAUSED), ("stop", S.DONE), ("ignore", S.RUNNING)]
)
def test_losing_the_controlling_rider_applies_the_policy(policy: str, state: S) -> None:
    rig = _running(policy)
    rig.control.rider_lost(rig.clock())
    rig.step()
    assert rig.state is state
    assert rig.relays_on() is (state is S.RUNNING)
    assert not rig.control.rider_connected


def test_grace_period_waits_then_pauses() -> None:
    rig = _running("pause", grace_s=0.5)
    rig.control.rider_lost(rig.clock())
    rig.step(int(0.4 / rig.period))
    assert rig.state is S.RUNNING
    rig.run_to_state(S.PAUSED, max_s=0.2)
    assert not rig.relays_on()
    assert rig.control.rider_warning is not None


def test_rider_back_within_grace_changes_nothing() -> None:
    rig = _running("pause", grace_s=0.5)
    rig.control.rider_lost(rig.clock())
    rig.step(10)
    rig.control.rider_back()
    rig.step(int(1.0 / rig.period))
    assert rig.state is S.RUNNING
    assert rig.control.rider_connected


def test_loss_outside_motion_does_nothing() -> None:
    rig = Rig().ready()
    rig.control.rider_lost(rig.clock())
    rig.step(10)
    assert rig.state is S.IDLE


def test_resume_by_another_rider_clears_the_rider_lost_warning() -> None:
    rig = _running("pause")
    rig.control.rider_lost(rig.clock())
    rig.step()
    assert rig.control.rider_warning is not None
    assert rig.send(Command.RESUME, rider="r2").success
    assert rig.control.rider_warning is None
    assert rig.control.controller_rider == "r2"
