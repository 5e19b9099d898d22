"""A whole ride over real Zenoh: the daemon (simulator) in its own process, this test as the Rider.

calibrate → home → start → DONE, pause / resume, stop, and an E-stop injected through the
simulator's fault queryable; the simulated world (`sim/world`) is the ground truth for what
moved.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from ride_machine.rider.client import CommandRefused, Rider
from ride_machine.schema.commands import ReplyCode
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import (
    STEP_TIMEOUT_S,
    again_after_stall,
    module_machine,
    not_spoiled,
    not_stalled,
    prepare,
    relays_off,
    settle,
    wait_cycles,
    wait_revolutions,
)
from tests.procs import Daemon

pytestmark = pytest.mark.integration

REVOLUTION_SLACK = 0.1
"""The rotate axis stops on the home switch: a session of 3 travels 3 revolutions ± a bit."""

TILT_SLACK_DEG = 2.0
"""Tilt ends within the controller's tolerance (1°) of 45° as it sees it; the world's
truth differs by the calibration error on top."""

QUIET_CYCLES = 20
"""Scan cycles to watch for unwanted motion (paused, stopped, E-stop released)."""


machine = module_machine("session")


@pytest.fixture
def rider(machine: Daemon) -> Iterator[Rider]:
    with machine.rider() as r:
        yield r


def holds_still(rider: Rider, since: SimWorldState) -> None:
    """Nothing moves for a while after `since`, and the relays stay off."""
    wait_cycles(rider, QUIET_CYCLES)
    now = rider.sim("world")
    assert (now.revolutions, now.tilt_deg) == (since.revolutions, since.tilt_deg)
    assert relays_off(rider)


def run_to_done(rider: Rider, after: float) -> list[Status]:
    """Every status until DONE (bounded); fails on any other resting or fault state (one the
    machine put down to its scan's stall: `HostStalled`, and the test rides again)."""
    seen: list[Status] = []
    for update in rider.watch(("status",), timeout=STEP_TIMEOUT_S):
        if not isinstance(update, Status) or update.time < after:
            continue
        seen.append(not_stalled(update))
        if update.state is MachineState.DONE:
            return seen
        assert update.state in (MachineState.RUNNING, MachineState.PAUSED), (
            f"{update.state} {update.fault} after {seen[:-1][-3:]}"
        )
    raise AssertionError(f"no DONE; last status {seen[-1] if seen else None}")


def resume_to_done(rider: Rider, before: SimWorldState) -> Status:
    """Resume; the default session started at `before` ends DONE, 3 revolutions in all."""
    reply = rider.resume()
    assert reply.code is ReplyCode.RESP_RESUMED
    assert reply.state is MachineState.RUNNING
    final = run_to_done(rider, reply.timecode)[-1]
    assert final.session is not None and final.session.revolutions_done == 3
    world = rider.sim("world")
    assert world.revolutions - before.revolutions == pytest.approx(3.0, abs=REVOLUTION_SLACK)
    return final


def one_revolution_in(rider: Rider) -> SimWorldState:
    """Prepared, the default session started and one revolution done; the world before it."""
    prepare(rider)
    before = rider.sim("world")
    wait_revolutions(rider, rider.start(), 1)
    return before


def test_calibrate_home_start_runs_the_default_session_to_done(rider: Rider) -> None:
    again_after_stall(lambda: calibrate_home_and_ride(rider))


def calibrate_home_and_ride(rider: Rider) -> None:
    reply = rider.calibrate_tilt()
    assert reply.code is ReplyCode.RESP_CALIBRATION_ACCEPTED
    assert reply.state is MachineState.CALIBRATING
    assert not_spoiled(settle(rider, reply)).calibrated.tilt

    reply = rider.calibrate_rotate()
    assert reply.state is MachineState.CALIBRATING
    status = not_spoiled(settle(rider, reply))
    assert status.calibrated.tilt and status.calibrated.rotate

    reply = rider.home()
    assert reply.code is ReplyCode.RESP_HOME_ACCEPTED
    status = not_spoiled(settle(rider, reply))
    assert status.state is MachineState.IDLE
    assert status.homed.tilt and status.homed.rotate

    before = rider.sim("world")
    reply = rider.start()
    assert reply.code is ReplyCode.RESP_START_ACCEPTED
    assert reply.state is MachineState.RUNNING
    seen = run_to_done(rider, reply.timecode)

    final = seen[-1]
    assert final.session is not None
    assert (final.session.revolutions_done, final.session.revolutions_total) == (3, 3)
    assert final.session.step_index == final.session.step_count
    progress = [s.session.revolutions_done for s in seen if s.session is not None]
    assert progress == sorted(progress), "revolutions never count backwards"
    assert final.tilt_deg == pytest.approx(45.0, abs=1.0)
    world = rider.sim("world")
    assert world.revolutions - before.revolutions == pytest.approx(3.0, abs=REVOLUTION_SLACK)
    assert world.tilt_deg == pytest.approx(45.0, abs=TILT_SLACK_DEG)
    assert relays_off(rider)


def test_pause_holds_with_relays_off_and_resume_finishes_the_session(rider: Rider) -> None:
    again_after_stall(lambda: pause_and_resume(rider))


def pause_and_resume(rider: Rider) -> None:
    before = one_revolution_in(rider)
    reply = rider.pause()
    assert reply.code is ReplyCode.RESP_PAUSED
    paused = rider.wait_for({MachineState.PAUSED}, STEP_TIMEOUT_S, after=reply.timecode)
    assert paused.previous_state is MachineState.RUNNING
    assert relays_off(rider)
    holds_still(rider, rider.sim("world"))
    assert rider.status().state is MachineState.PAUSED

    resume_to_done(rider, before)


def test_stop_ends_the_session_done_and_nothing_moves(rider: Rider) -> None:
    again_after_stall(lambda: stop_mid_ride(rider))


def stop_mid_ride(rider: Rider) -> None:
    one_revolution_in(rider)
    reply = rider.stop()
    assert reply.code is ReplyCode.RESP_DONE
    done = rider.wait_for({MachineState.DONE}, STEP_TIMEOUT_S, after=reply.timecode)
    assert done.session is None, "stop clears the session"
    assert relays_off(rider)
    holds_still(rider, rider.sim("world"))
    with pytest.raises(CommandRefused) as refused:
        rider.resume()
    assert refused.value.error.code is ErrorCode.WRONG_STATE


@pytest.mark.hazard("H10")
def test_estop_from_the_simulator_latches_release_moves_nothing_resume_continues(
    rider: Rider,
) -> None:
    again_after_stall(lambda: estop_mid_ride(rider))


def estop_mid_ride(rider: Rider) -> None:
    before = one_revolution_in(rider)
    pressed = rider.sim("estop", pressed=True)
    assert pressed.estop_pressed
    fault = rider.wait_for({MachineState.FAULT_ESTOP}, STEP_TIMEOUT_S, after=pressed.time)
    assert fault.previous_state is MachineState.RUNNING
    assert fault.estop.active and fault.estop.latched
    assert relays_off(rider)
    for command in (rider.resume, rider.start, rider.home):
        with pytest.raises(CommandRefused) as refused:
            command()
        assert refused.value.error.code is ErrorCode.ESTOP_ACTIVE

    released = rider.sim("estop", pressed=False)
    assert not released.estop_pressed
    for update in rider.watch(("status",), timeout=STEP_TIMEOUT_S):
        if isinstance(update, Status) and not update.estop.active:
            break
    else:
        raise AssertionError("the released E-stop never showed in the status")
    assert update.state is MachineState.FAULT_ESTOP, "release alone changes nothing"
    assert update.estop.latched
    holds_still(rider, released)
    assert relays_off(rider)
    assert rider.status().state is MachineState.FAULT_ESTOP

    assert not resume_to_done(rider, before).estop.latched
