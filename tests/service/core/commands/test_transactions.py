"""At-most-once transaction ids: a repeated id gets the same reply and acts once, a reused one
for another command is refused, and the window forgets the oldest and holds no objects for the
garbage collector (moved from test_control.py)."""

from __future__ import annotations

import gc

import pytest

from ride_machine.schema.codec import Format, encode
from ride_machine.schema.commands import Command, ReplyCode
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from tests.rig import Rig, known_calibration, rig_in

S = MachineState
C = Command
E = ErrorCode
R = ReplyCode


@pytest.mark.hazard("H26")
def test_repeated_transaction_id_gets_the_same_reply_and_does_not_act_twice() -> None:
    rig = rig_in(S.IDLE)
    first = rig.send(C.START, transaction_id="start-1")
    assert first.success
    rig.step(20)
    assert rig.send(C.PAUSE, transaction_id="pause-1").success
    transitions = len(rig.transitions)

    again = rig.send(C.START, transaction_id="start-1")

    assert again == first
    assert rig.state is S.PAUSED  # the retry did not start anything
    assert len(rig.transitions) == transitions
    assert rig.loop.transactions.repeats == 1


def test_repeated_home_does_not_restart_homing() -> None:
    rig = rig_in(S.WARNING_NOT_HOME)
    first = rig.send(C.HOME, transaction_id="home-1")
    rig.step(30)
    progress = rig.hal.world.tilt_deg
    again = rig.send(C.HOME, transaction_id="home-1")
    assert again == first
    assert again.success  # the original answer, although Home is refused while HOMING
    rig.step()
    assert rig.hal.world.tilt_deg < progress  # still on its way down, not restarted
    assert [t.new for t in rig.transitions].count(S.HOMING) == 1


def test_repeated_refusal_stays_a_refusal() -> None:
    rig = rig_in(S.WARNING_NOT_HOME)
    first = rig.send(C.START, transaction_id="s-1")
    assert first.error is not None
    assert first.error.code is E.NOT_HOME
    rig.home()
    again = rig.send(C.START, transaction_id="s-1")
    assert again == first
    assert rig.state is S.IDLE


@pytest.mark.hazard("H26")
def test_same_transaction_id_for_another_command_is_refused() -> None:
    rig = rig_in(S.IDLE)
    assert rig.send(C.START, transaction_id="tx-9").success
    state = rig.state

    reply = rig.send(C.STOP, transaction_id="tx-9")

    assert not reply.success
    assert reply.error is not None
    assert reply.error.code is E.DUPLICATE_TRANSACTION
    assert reply.error.path == "/transaction_id"
    assert "Start" in reply.error.message
    assert reply.command == C.STOP.value
    assert rig.state is state  # Stop did not act
    rig.step(10)
    assert rig.relays_on()


def test_transaction_window_forgets_the_oldest_id() -> None:
    config = MachineConfig().with_overrides(bus={"transaction_window": 2})
    rig = Rig(config=config, calibration=known_calibration())
    rig.send(C.CHECK_HOME, transaction_id="a")
    rig.send(C.CHECK_HOME, transaction_id="b")
    rig.send(C.CHECK_HOME, transaction_id="c")
    assert len(rig.loop.transactions) == 2
    # "a" fell out of the window: a different command may use it and is acted on.
    reply = rig.send(C.STOP, transaction_id="a")
    assert reply.success
    assert reply.code is R.RESP_DONE
    # "c" is still remembered.
    assert rig.send(C.STOP, transaction_id="c").error is not None


def test_the_transaction_window_holds_no_objects_for_the_garbage_collector() -> None:
    """Thousands of remembered replies turning over at the command rate, kept as models, made
    every full collection long; kept as bytes, the collector never looks at them."""
    rig = Rig(calibration=known_calibration())
    first = rig.send(C.CHECK_HOME, transaction_id="gc-0")
    for i in range(1, 50):
        rig.send(C.CHECK_HOME, transaction_id=f"gc-{i}")
    gc.collect()
    entries = gc.get_referents(rig.loop.transactions._replies)
    assert len(entries) >= 50
    assert not any(gc.is_tracked(e) for e in entries)
    assert rig.send(C.CHECK_HOME, transaction_id="gc-0") == first  # read back whole


def test_a_reply_goes_out_as_the_bytes_its_window_keeps_and_no_other_does() -> None:
    """One serialisation per command: the reply recorded last is sent as its window's bytes;
    a refusal of a reused id, or a reply once a later one is recorded, is encoded afresh."""
    rig = Rig(calibration=known_calibration())
    window = rig.loop.transactions
    first = rig.send(C.CHECK_HOME, transaction_id="w-1")
    assert window.wire(first) == encode(first, Format.MSGPACK)
    reused = rig.send(C.STOP, transaction_id="w-1")
    assert reused.error is not None
    assert reused.error.code is ErrorCode.DUPLICATE_TRANSACTION
    assert window.wire(reused) is None  # never the first command's bytes
    repeat = rig.send(C.CHECK_HOME, transaction_id="w-1")
    assert repeat == first
    assert window.wire(repeat) is None  # read back: equal, not the same object
    later = rig.send(C.CHECK_HOME, transaction_id="w-2")
    assert window.wire(first) is None
    assert window.wire(later) == encode(later, Format.MSGPACK)
