"""The event recorder: the exact events a ride produces, in order, from the steppable loop."""

from __future__ import annotations

import logging
import threading

import pytest

from ride_machine.schema.calibration import CalibrationSet
from ride_machine.schema.commands import Command, CommandRequest, RotateStep, Session, TiltStep
from ride_machine.schema.events import (
    CalibrationEvent,
    CommandEvent,
    CompletionEvent,
    EstopEvent,
    FaultEvent,
    KnownDetails,
    SessionEndedEvent,
    SessionStartedEvent,
    StateEvent,
    StorageEvent,
)
from ride_machine.schema.status import MachineState
from ride_machine.service.core.history.events import ListEventSink
from ride_machine.service.core.history.facts import CommandFacts
from ride_machine.service.core.history.held import Held, hold_limit
from ride_machine.service.core.storage.persist import StorageHealth
from tests.rig import Rig, known_calibration

S = MachineState
SHORT = Session(name="short", steps=[TiltStep(degrees=10.0), RotateStep(revolutions=1)])


def kinds(sink: ListEventSink, start: int = 0) -> list[str]:
    return [d.kind for d, _, _ in sink.events[start:]]


def details(sink: ListEventSink, start: int = 0) -> list[KnownDetails]:
    return [d for d, _, _ in sink.events[start:]]


def ready_rig(*, guarded: bool = False) -> tuple[Rig, ListEventSink]:
    sink = ListEventSink()
    rig = Rig(calibration=known_calibration(), events=sink, guarded=guarded)
    rig.home()
    return rig, sink


def test_a_session_records_command_transition_start_end_and_completion_in_order() -> None:
    rig, sink = ready_rig()
    mark = len(sink.events)
    reply = rig.send(Command.START, session=SHORT.model_dump())
    rig.run_to_state(S.DONE)
    assert kinds(sink, mark) == [
        "command",
        "state",
        "session_started",
        "state",
        "session_ended",
        "completion",
    ]
    cmd, start, started, end, ended, done = details(sink, mark)
    assert isinstance(cmd, CommandEvent) and cmd.accepted
    assert (cmd.command, cmd.transaction_id, cmd.code) == (
        "Start",
        reply.transaction_id,
        "RESP_START_ACCEPTED",
    )
    assert isinstance(start, StateEvent) and (start.old, start.new) == (S.IDLE, S.RUNNING)
    assert isinstance(started, SessionStartedEvent)
    assert (started.name, started.steps, started.revolutions_total) == ("short", 2, 1)
    assert isinstance(end, StateEvent) and end.reason == "session complete"
    assert isinstance(ended, SessionEndedEvent)
    assert (ended.outcome, ended.steps_done, ended.revolutions_done) == ("DONE", 2, 1)
    assert ended.duration_s > 0
    assert isinstance(done, CompletionEvent)
    assert (done.command, done.transaction_id, done.outcome) == (
        "Start",
        reply.transaction_id,
        "DONE",
    )
    # Every event carries the cycle it happened in, never decreasing.
    cycles = [c for _, _, c in sink.events[mark:]]
    assert cycles == sorted(cycles) and cycles[-1] == rig.loop.cycle


def test_estop_mid_session_then_resume_records_press_latch_release_and_reset() -> None:
    rig, sink = ready_rig()
    rig.send(Command.START, session=SHORT.model_dump())
    rig.step(20)
    mark = len(sink.events)
    rig.hal.press_estop()
    rig.step()
    assert kinds(sink, mark) == ["estop_pressed", "state", "estop_latched"]
    rig.step(5)
    assert kinds(sink, mark) == ["estop_pressed", "state", "estop_latched"]  # once, not per cycle
    rig.hal.release_estop()
    rig.step()
    resumed = rig.send(Command.RESUME)
    assert resumed.success
    rig.run_to_state(S.DONE)
    assert kinds(sink, mark) == [
        "estop_pressed",
        "state",
        "estop_latched",
        "estop_released",
        "command",
        "state",
        "estop_reset",
        "state",
        "session_ended",
        "completion",
    ]
    reset = details(sink, mark)[6]
    assert isinstance(reset, EstopEvent) and reset.reason == "Resume"
    ended = details(sink, mark)[-2]
    assert isinstance(ended, SessionEndedEvent) and ended.outcome == "DONE"


def test_a_fault_records_raise_session_end_and_completion_then_clear_on_recovery() -> None:
    rig, sink = ready_rig()
    rig.send(Command.START, session=SHORT.model_dump())
    rig.step(5)
    rig.hal.stall("tilt")
    mark = len(sink.events)
    rig.run_to_state(S.FAULT_HW)
    assert kinds(sink, mark) == ["state", "fault_raised", "session_ended", "completion"]
    raised, ended, done = details(sink, mark)[1:]
    assert isinstance(raised, FaultEvent) and raised.code == "TILT_NOT_FOLLOWING"
    assert raised.axis == "tilt"
    assert isinstance(ended, SessionEndedEvent) and ended.outcome == "FAULT_HW"
    assert isinstance(done, CompletionEvent) and done.outcome == "FAULT_HW"
    assert done.state is S.FAULT_HW
    rig.hal.clear_faults()
    mark = len(sink.events)
    assert rig.send(Command.HOME).success
    assert kinds(sink, mark)[:3] == ["command", "state", "fault_cleared"]


def test_refused_and_repeated_commands_are_recorded_as_such() -> None:
    rig, sink = ready_rig()
    mark = len(sink.events)
    refused = rig.send(Command.PAUSE)
    assert not refused.success
    rig.send(Command.CHECK_HOME, transaction_id="same")
    rig.send(Command.CHECK_HOME, transaction_id="same")
    first, check, again = details(sink, mark)
    assert isinstance(first, CommandEvent) and not first.accepted
    assert first.code == "WRONG_STATE" and "Pause" in first.message
    assert isinstance(check, CommandEvent) and check.accepted and not check.repeat
    assert isinstance(again, CommandEvent) and again.repeat


def test_stop_while_paused_ends_the_session_as_stopped() -> None:
    rig, sink = ready_rig()
    rig.send(Command.START, session=SHORT.model_dump())
    rig.step(5)
    rig.send(Command.PAUSE)
    mark = len(sink.events)
    rig.send(Command.STOP)
    assert kinds(sink, mark) == ["command", "state", "session_ended", "completion"]
    ended, done = details(sink, mark)[2:]
    assert isinstance(ended, SessionEndedEvent) and ended.outcome == "STOPPED"
    assert isinstance(done, CompletionEvent) and done.outcome == "STOPPED"


def test_calibration_records_old_and_new_values_per_axis() -> None:
    sink = ListEventSink()
    rig = Rig(events=sink)
    rig.calibrate()
    cals = [d for d in details(sink) if isinstance(d, CalibrationEvent)]
    assert [c.axis for c in cals] == ["tilt", "rotate"]
    assert cals[0].old is None and cals[0].new is not None
    assert cals[0].new["gain_counts_per_deg"] > 0
    assert not cals[0].persisted  # no store in this rig
    completions = [d for d in details(sink) if isinstance(d, CompletionEvent)]
    assert [(c.command, c.outcome) for c in completions] == [
        ("CalibrateTilt", "DONE"),
        ("CalibrateRotate", "DONE"),
    ]


def test_an_idle_machine_records_nothing() -> None:
    rig, sink = ready_rig()
    mark = len(sink.events)
    rig.step(500)
    assert kinds(sink, mark) == []


def test_a_failed_write_to_data_dir_is_recorded_once_per_problem() -> None:
    rig, sink = ready_rig()
    storage = StorageHealth()
    rig.state_machine.storage = storage  # what the daemon wires in (service/supervision/daemon.py)
    mark = len(sink.events)
    storage.failed(StorageHealth.CALIBRATION, "calibration.json: No space left on device")
    rig.step(3)
    [problem] = details(sink, mark)
    assert isinstance(problem, StorageEvent) and "No space left" in problem.error
    storage.recovered(StorageHealth.CALIBRATION)
    rig.step()
    storage.failed(StorageHealth.PARAMS, "params.json: Read-only file system")
    rig.step()
    assert [d.kind for d in details(sink, mark)] == ["storage_failed", "storage_failed"]


def tripped_while_homing() -> tuple[Rig, ListEventSink, str, int]:
    """A homing machine whose watchdog has just latched the outputs safe (what its thread does
    when the loop stalls); returns the rig, its events, the Home's transaction and the mark."""
    rig, sink = ready_rig(guarded=True)
    assert rig.guard is not None
    home = rig.send(Command.HOME)
    rig.step(3)
    mark = len(sink.events)
    rig.guard.latch_safe()
    return rig, sink, home.transaction_id or "", mark


def assert_watchdog_ended(raised: object, done: object, transaction_id: str) -> None:
    assert isinstance(raised, FaultEvent) and raised.code == "WATCHDOG"
    assert isinstance(done, CompletionEvent) and done.transaction_id == transaction_id
    assert done.outcome == "FAULT_HW" and done.code == "WATCHDOG"


def test_a_watchdog_trip_ends_the_motion_with_a_recorded_fault() -> None:
    rig, sink, home, mark = tripped_while_homing()
    rig.step()
    assert kinds(sink, mark) == ["state", "fault_raised", "completion"]
    assert_watchdog_ended(*details(sink, mark)[1:], home)


def test_a_command_right_after_a_watchdog_trip_is_recorded_after_the_fault() -> None:
    """Home sent on the watchdog's FAULT_HW before the next cycle: the history says fault,
    then the old motion's end, then the command (accepted against the fault)."""
    rig, sink, home, mark = tripped_while_homing()
    request = CommandRequest.model_validate({"transaction_id": "home-after-trip"})
    reply = rig.port.execute(Command.HOME, request, sender=None, timeout=1.0)
    assert reply is not None and reply.success
    rig.step()  # a command answered between cycles is written with the next one
    assert kinds(sink, mark)[:4] == ["state", "fault_raised", "completion", "command"]
    raised, done, cmd = details(sink, mark)[1:4]
    assert_watchdog_ended(raised, done, home)
    assert isinstance(cmd, CommandEvent) and cmd.transaction_id == "home-after-trip"


def test_calibration_entered_by_hand_is_recorded_old_to_new() -> None:
    rig, sink = ready_rig()
    before = rig.state_machine.calibration.tilt
    assert before is not None
    mark = len(sink.events)
    values = {"offset_counts": before.offset_counts + 10, "gain_counts_per_deg": 41.0}
    rig.state_machine.enter_calibration(
        CalibrationSet.model_validate({"transaction_id": "c1", "tilt": values}), rig.clock()
    )
    rig.step()
    [cal] = [d for d in details(sink, mark) if isinstance(d, CalibrationEvent)]
    assert cal.axis == "tilt" and cal.old is not None and cal.new is not None
    assert cal.old["offset_counts"] == before.offset_counts
    assert cal.new["offset_counts"] == before.offset_counts + 10


def between_cycles(rig: Rig, command: Command, tid: str) -> None:
    """A command the way the bus runs it: in a Zenoh callback, between two cycles."""
    request = CommandRequest.model_validate({"transaction_id": tid})
    reply = rig.port.execute(command, request, sender=None, timeout=1.0)
    assert reply is not None


def test_a_command_between_cycles_is_written_with_the_next_cycle_and_before_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Its reply goes out first; its events and log line follow at the next cycle, once the
    outputs are written, and before anything that cycle records."""
    rig, sink = ready_rig()
    mark = len(sink.events)
    caplog.set_level(logging.INFO, logger="machine")
    caplog.clear()
    between_cycles(rig, Command.START, "ride")
    assert kinds(sink, mark) == []
    assert "event=command" not in caplog.text
    rig.step()
    assert kinds(sink, mark)[:3] == ["command", "state", "session_started"]
    assert "event=command tx=ride command=Start" in caplog.text


def test_held_records_keep_their_order_with_any_later_event() -> None:
    rig, sink = ready_rig()
    mark = len(sink.events)
    between_cycles(rig, Command.CHECK_HOME, "first")
    between_cycles(rig, Command.START, "second")  # its transition follows the first command
    rig.loop.recorder.emit(StorageEvent(what="data_dir", error="x"), rig.clock())
    assert kinds(sink, mark) == ["command", "command", "state", "session_started", "storage_failed"]
    assert [getattr(d, "transaction_id", None) for d in details(sink, mark)[:2]] == [
        "first",
        "second",
    ]


def test_a_command_storm_between_cycles_leaves_the_cycle_a_bounded_share() -> None:
    """Beyond the period's share (10 commands at 10 ms) each command hands over the oldest one
    held itself: the order stays, and the next cycle has at most its share to do."""
    rig, sink = ready_rig()
    limit = rig.loop.recorder.hold_limit
    assert limit == hold_limit(rig.config.loop.period_s) == 10
    mark = len(sink.events)
    for i in range(limit):
        between_cycles(rig, Command.CHECK_HOME, f"c{i}")
    assert kinds(sink, mark) == []
    for i in range(limit, limit + 5):
        between_cycles(rig, Command.CHECK_HOME, f"c{i}")
    assert [d.transaction_id for d in details(sink, mark)] == [f"c{i}" for i in range(5)]
    rig.step()
    assert [d.transaction_id for d in details(sink, mark)] == [f"c{i}" for i in range(15)]
    assert hold_limit(0.001) == 1 and hold_limit(0.05) == 50


class DeferringSink(ListEventSink):
    """Takes held records as the event log does (`EventLog.defer`), to make them later."""

    def __init__(self) -> None:
        super().__init__()
        self.deferred: list[Held] = []

    def defer(self, held: Held) -> bool:
        self.deferred.append(held)
        return True


def test_a_sink_that_defers_gets_the_held_records_unmade_and_in_order(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """With the event log, the cycle (or a command past the cycle's share) only passes the
    record on: no event is made and no log line written on the scan or the command thread;
    made later, they are the events and the line the command's state gave, in order."""
    sink = DeferringSink()
    rig = Rig(calibration=known_calibration(), events=sink)
    rig.home()
    caplog.set_level(logging.INFO, logger="machine")
    caplog.clear()
    made, passed = len(sink.events), len(sink.deferred)
    between_cycles(rig, Command.CHECK_HOME, "first")
    between_cycles(rig, Command.START, "second")
    rig.step()
    assert len(sink.events) == made  # nothing made on this thread
    assert "event=command" not in caplog.text
    assert len(sink.deferred) == passed + 2
    for held in sink.deferred[passed:]:
        held.write(sink.emit)
    assert kinds(sink, made)[:4] == ["command", "command", "state", "session_started"]
    assert [getattr(d, "transaction_id", None) for d in details(sink, made)][:2] == [
        "first",
        "second",
    ]
    assert "event=command tx=first" in caplog.text and "event=command tx=second" in caplog.text


def test_without_a_history_a_held_record_writes_its_log_line_and_makes_no_event(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`[events] enabled = false`: the command's line is logged, in order, and none of its
    events is made (they would only be dropped)."""
    made: list[str] = []
    make = CommandFacts.__call__

    def counting(facts: CommandFacts) -> CommandEvent:
        made.append(facts.transaction_id)
        return make(facts)

    monkeypatch.setattr(CommandFacts, "__call__", counting)
    rig = Rig(calibration=known_calibration())
    caplog.set_level(logging.INFO, logger="machine")
    between_cycles(rig, Command.CHECK_HOME, "first")
    between_cycles(rig, Command.CHECK_HOME, "second")
    rig.step()
    assert made == []
    lines = [r.getMessage() for r in caplog.records if "event=command" in r.getMessage()]
    assert [line.split()[1] for line in lines] == ["tx=first", "tx=second"]


def test_a_history_read_hands_over_held_records_unless_the_loop_is_stalled() -> None:
    rig, sink = ready_rig()
    mark = len(sink.events)
    between_cycles(rig, Command.CHECK_HOME, "asked-before")
    with rig.loop.lock:  # a cycle in progress that outlasts the read's patience
        done = threading.Thread(target=rig.port.release_records, args=(0.05,))
        done.start()
        done.join(5.0)
        assert not done.is_alive()
    assert kinds(sink, mark) == []  # nothing written behind the scan thread's back
    rig.port.release_records(0.05)
    assert kinds(sink, mark) == ["command"]


def test_the_shutdown_hands_over_what_is_held_before_the_motion_it_ends() -> None:
    """`machine run` winds down with `abort_motion`: a command answered after the last cycle
    is still in the history, before the aborted motion's end."""
    rig, sink = ready_rig()
    mark = len(sink.events)
    between_cycles(rig, Command.START, "last")
    rig.loop.abort_motion(rig.clock(), "machine daemon is shutting down")
    got = details(sink, mark)
    assert got[0].kind == "command" and getattr(got[0], "transaction_id", None) == "last"
    assert "completion" in kinds(sink, mark)
    assert kinds(sink, mark).index("completion") > 0
