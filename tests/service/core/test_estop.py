"""E-stop in every state at random (seeded) cycles: same-cycle safe outputs, latch, Resume, Home."""

from __future__ import annotations

import random

import pytest

from ride_machine.hal.iomap import IoMap
from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MOTION_STATES, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.tasks import PendingCommand
from tests.rig import Rig, known_calibration, rig_in

S = MachineState
C = Command
SEEDS = [3, 17, 2024]
CASES = [(state, seed) for state in S for seed in SEEDS]
IDS = [f"{state}-seed{seed}" for state, seed in CASES]
ROTATE_STEP_DEG = MachineConfig().hal.sim.rotate_speed_dps * MachineConfig().loop.period_s


def positions(rig: Rig) -> tuple[float, float, float]:
    w = rig.hal.world
    return (w.rotate_deg, w.rotate_travel_deg, w.tilt_deg)


def enter(state: MachineState) -> Rig:
    """A rig in `state` with the E-stop clear (FAULT_ESTOP: latched, already released)."""
    return rig_in(state, estop_held=False)


def press_at_random_cycle(rig: Rig, state: MachineState, seed: int) -> int:
    """Run 0..59 more cycles in `state` (none of the recipes' states ends sooner), then press."""
    cycles = random.Random(f"{state}/{seed}").randrange(60)
    for _ in range(cycles):
        rig.step()
        assert rig.state is state
    rig.hal.press_estop()
    return cycles


@pytest.mark.hazard("H09")
@pytest.mark.parametrize(("state", "seed"), CASES, ids=IDS)
def test_estop_drops_relays_in_the_same_cycle(state: MachineState, seed: int) -> None:
    rig = enter(state)
    press_at_random_cycle(rig, state, seed)
    statuses = len(rig.sink.statuses)
    writes = rig.hal.writes

    rig.step()  # the cycle whose input scan sees the E-stop

    assert not rig.relays_on()
    assert not any(rig.loop.image.outputs.ro.values())
    assert rig.state is S.FAULT_ESTOP
    assert rig.hal.writes == writes  # no normal output write in an E-stop cycle
    published = rig.sink.statuses[statuses:]
    assert published  # the fault is published in the same cycle, too
    assert published[-1].state == "FAULT_ESTOP"
    assert published[-1].estop.active
    assert published[-1].estop.latched


@pytest.mark.hazard("H09")
@pytest.mark.parametrize("state", sorted(MOTION_STATES))
def test_estop_cuts_a_relay_that_was_on(state: MachineState) -> None:
    rig = enter(state)
    rig.run_until(rig.relays_on)
    rig.hal.press_estop()
    rig.step()
    assert not rig.relays_on()
    assert rig.state is S.FAULT_ESTOP


@pytest.mark.hazard("H10")
@pytest.mark.parametrize(("state", "seed"), CASES, ids=IDS)
def test_release_alone_moves_nothing(state: MachineState, seed: int) -> None:
    rig = enter(state)
    press_at_random_cycle(rig, state, seed)
    rig.step(random.Random(seed).randrange(1, 50))
    held = positions(rig)
    rig.hal.release_estop()

    for _ in range(1000):  # ten seconds after release
        rig.step()
        assert not rig.relays_on()
    assert rig.state is S.FAULT_ESTOP
    assert positions(rig) == held
    status = rig.loop.published.status
    assert status is not None
    assert status.estop.active is False
    assert status.estop.latched is True


@pytest.mark.hazard("H10")
@pytest.mark.parametrize(("state", "seed"), CASES, ids=IDS)
def test_resume_after_release_returns_to_the_previous_state(state: MachineState, seed: int) -> None:
    rig = enter(state)
    back_to = S.IDLE if state is S.FAULT_ESTOP else state  # the recipe pressed it while IDLE
    travel0 = rig.hal.world.rotate_travel_deg
    fault = rig.state_machine.fault
    press_at_random_cycle(rig, state, seed)
    rig.step(20)
    refused = rig.send(C.RESUME)  # still held
    assert refused.error is not None
    assert refused.error.code is ErrorCode.ESTOP_ACTIVE
    rig.hal.release_estop()
    rig.step(20)

    reply = rig.send(C.RESUME)

    assert reply.success, reply.error
    assert reply.state is back_to
    assert rig.state is back_to
    assert rig.state_machine.estop_latched is False
    assert rig.state_machine.fault == fault
    if state is S.PAUSED:
        assert rig.send(C.RESUME).state is S.RUNNING
    if state in (S.RUNNING, S.PAUSED):
        rig.run_to_state(S.DONE, S.FAULT_HW)
        assert rig.state is S.DONE, rig.state_machine.fault
        turned = rig.hal.world.rotate_travel_deg - travel0
        assert turned == pytest.approx(1080.0, abs=ROTATE_STEP_DEG)
    elif state is S.HOMING:
        rig.run_to_state(S.IDLE, S.FAULT_HW)
        assert rig.state is S.IDLE, rig.state_machine.fault
    elif state is S.CALIBRATING:
        rig.run_until(lambda: rig.state is not S.CALIBRATING)
        assert rig.state_machine.calibration.tilt is not None, rig.state_machine.fault
        assert rig.state is S.WARNING_NEEDS_CALIBRATION  # rotate still to calibrate
    else:
        rig.step(100)
        assert rig.state is back_to
        assert not rig.relays_on()


@pytest.mark.parametrize(("state", "seed"), CASES, ids=IDS)
def test_home_after_release_rehomes(state: MachineState, seed: int) -> None:
    rig = enter(state)
    press_at_random_cycle(rig, state, seed)
    rig.step(5)
    assert rig.send(C.HOME).error is not None  # refused while held
    rig.hal.release_estop()
    rig.step()

    reply = rig.send(C.HOME)

    assert reply.success, reply.error
    assert rig.state is S.HOMING
    rig.run_until(lambda: rig.state is not S.HOMING)
    calibrated = rig.state_machine.calibration.complete
    assert rig.state is (S.IDLE if calibrated else S.WARNING_NEEDS_CALIBRATION), (
        rig.state_machine.fault
    )
    assert rig.state_machine.keeper.homed().tilt
    assert rig.state_machine.keeper.homed().rotate
    assert rig.state_machine.context.drive.session_run is None
    assert not rig.relays_on()


@pytest.mark.parametrize("seed", range(5))
def test_estops_anywhere_in_a_session_keep_the_revolution_count(seed: int) -> None:
    rig = enter(S.IDLE)
    rng = random.Random(seed)
    travel0 = rig.hal.world.rotate_travel_deg
    assert rig.send(C.START).success
    presses = 0
    while rig.state is not S.DONE:
        rig.step(rng.randrange(1, 400))
        if rig.state is S.DONE:
            break
        assert rig.state is S.RUNNING, rig.state_machine.fault
        rig.hal.press_estop()
        rig.step()
        assert not rig.relays_on()
        rig.step(rng.randrange(0, 100))
        rig.hal.release_estop()
        rig.step(rng.randrange(1, 100))
        assert rig.send(C.RESUME).state is S.RUNNING
        presses += 1
    assert presses >= 2
    turned = rig.hal.world.rotate_travel_deg - travel0
    assert turned == pytest.approx(1080.0, abs=ROTATE_STEP_DEG)
    assert rig.hal.world.tilt_deg == pytest.approx(45.0, abs=MachineConfig().tilt.tolerance_deg)


@pytest.mark.hazard("H09")
def test_command_queued_in_the_estop_cycle_is_refused_in_that_cycle() -> None:
    rig = enter(S.IDLE)
    got: list[Reply] = []
    rig.loop.inbox.put(PendingCommand(C.START, CommandRequest(transaction_id="q1"), got.append))
    rig.loop.inbox.put(
        PendingCommand(C.CHECK_HOME, CommandRequest(transaction_id="q2"), got.append)
    )
    rig.hal.press_estop()
    rig.step()
    assert [r.transaction_id for r in got] == ["q1", "q2"]
    assert got[0].error is not None
    assert got[0].error.code is ErrorCode.ESTOP_ACTIVE
    assert got[0].state is S.FAULT_ESTOP
    assert got[1].success
    assert not rig.relays_on()


def test_stop_after_release_clears_the_latch() -> None:
    rig = enter(S.RUNNING)
    rig.hal.press_estop()
    rig.step()
    assert rig.send(C.STOP).error is not None  # refused while held
    rig.hal.release_estop()
    rig.step()
    assert rig.send(C.STOP).state is S.DONE
    assert rig.state_machine.estop_latched is False
    assert rig.state_machine.context.drive.session_run is None
    rig.step(100)
    assert not rig.relays_on()


@pytest.mark.hazard("H11")
@pytest.mark.parametrize("active_low", [True, False])
def test_estop_polarity_comes_from_the_io_map(active_low: bool) -> None:
    config = MachineConfig().with_overrides(hal={"iomap": {"estop_active_low": active_low}})
    rig = Rig(config=config, calibration=known_calibration())
    rig.home()
    channel = IoMap(estop_active_low=active_low).estop
    assert rig.loop.image.inputs.di[channel] is active_low  # released
    rig.send(C.START)
    rig.step(10)
    assert rig.relays_on()
    rig.hal.press_estop()
    rig.step()
    assert rig.loop.image.inputs.di[channel] is not active_low
    assert rig.state is S.FAULT_ESTOP
    assert not rig.relays_on()
