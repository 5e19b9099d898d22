"""A motion command that reaches the machine after its sender stopped waiting is not acted on.

The sender says how long it waits (`valid_for`, from its `timecode`); a daemon that was frozen or
cut off and resumes must not home, start or resume on a command its operator was told had
timed out."""

from __future__ import annotations

import time

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from tests.rig import Rig

MOTION = [Command.HOME, Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE]


def wall(rig: Rig) -> float:
    return rig.clock() + rig.state_machine.wall_offset


@pytest.mark.hazard("H27")
@pytest.mark.parametrize("command", MOTION)
def test_a_motion_command_older_than_its_wait_is_refused_and_nothing_moves(
    command: Command,
) -> None:
    rig = Rig()
    before = rig.state
    reply = rig.send(command, timecode=wall(rig) - 5.0, valid_for=2.0)
    assert not reply.success and reply.error is not None
    assert reply.error.code is ErrorCode.STALE_REQUEST
    assert "sent 5.0 s ago" in reply.error.message and "after 2 s" in reply.error.message
    rig.step(20)
    assert rig.state is before and not rig.relays_on()


def test_within_its_wait_and_the_clock_margin_it_is_taken() -> None:
    rig = Rig()
    margin = rig.config.bus.clock_margin_s
    assert rig.send(Command.HOME, timecode=wall(rig) - 2.0 - margin + 0.1, valid_for=2.0).success
    assert rig.state is MachineState.HOMING


def test_without_a_time_or_a_wait_no_age_is_judged() -> None:
    rig = Rig()
    assert rig.send(Command.HOME, timecode=wall(rig) - 600.0).success  # no valid_for
    rig = Rig()
    assert rig.send(Command.HOME, valid_for=0.5).success  # no timecode


@pytest.mark.hazard("H27")
def test_stop_pause_and_checks_are_never_refused_for_age() -> None:
    rig = Rig(calibration=None).ready()
    assert rig.send(Command.START, timecode=wall(rig), valid_for=2.0).success
    rig.step(5)
    old = {"timecode": wall(rig) - 60.0, "valid_for": 1.0}
    assert rig.send(Command.PAUSE, **old).success
    assert rig.send(Command.CHECK_HOME, **old).success
    assert rig.send(Command.STOP, **old).success
    assert rig.state is MachineState.DONE


def test_the_margin_is_a_setting() -> None:
    config = MachineConfig().with_overrides(bus={"clock_margin_s": 120.0})
    rig = Rig(config)
    assert rig.send(Command.HOME, timecode=wall(rig) - 60.0, valid_for=2.0).success


# ------------------------------------------------------------------------ one clock, seconds
@pytest.mark.hazard("H28")
@pytest.mark.parametrize("command", [*MOTION, Command.START])
def test_a_timecode_in_milliseconds_is_refused_whatever_its_wait(command: Command) -> None:
    """Issue 43, point 2: a JavaScript Rider's `Date.now()` (ms) 30 s ago with `valid_for: 5`
    was 1000 times "in the future" and passed the stale check; it is refused and says why."""
    rig = Rig()
    before = rig.state
    for valid_for in (5.0, None):
        sent_ms = round((time.time() - 30.0) * 1000)  # a Date.now() of 30 s ago
        reply = rig.send(command, timecode=sent_ms, valid_for=valid_for)
        assert not reply.success and reply.error is not None
        assert reply.error.code is ErrorCode.BAD_TIMECODE and reply.error.path == "/timecode"
        assert "milliseconds" in reply.error.message and "Date.now() / 1000" in reply.error.message
    rig.step(20)
    assert rig.state is before and not rig.relays_on()


@pytest.mark.hazard("H28")
def test_a_timecode_ahead_of_the_clock_by_more_than_the_margin_is_refused() -> None:
    """A captured or pre-made request "a day in the future" stayed fresh for a day."""
    rig = Rig()
    margin = rig.config.bus.clock_margin_s
    reply = rig.send(Command.HOME, timecode=wall(rig) + 86_400.0, valid_for=5.0)
    assert not reply.success and reply.error is not None
    assert reply.error.code is ErrorCode.BAD_TIMECODE
    assert "86400.0 s ahead" in reply.error.message and "clock_margin_s" in reply.error.message
    assert rig.state is not MachineState.HOMING
    assert rig.send(Command.HOME, timecode=wall(rig) + margin - 0.1, valid_for=5.0).success


def test_stop_and_pause_are_taken_whatever_their_timecode_says() -> None:
    rig = Rig(calibration=None).ready()
    assert rig.send(Command.START, timecode=wall(rig), valid_for=2.0).success
    rig.step(5)
    assert rig.send(Command.PAUSE, timecode=wall(rig) * 1000).success
    assert rig.send(Command.STOP, timecode=wall(rig) + 86_400.0).success
    assert rig.state is MachineState.DONE
