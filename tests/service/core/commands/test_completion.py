"""Completion notices on the fake clock: one per motion, how it ended, after its status."""

from __future__ import annotations

import tracemalloc
from dataclasses import dataclass
from typing import Any

from ride_machine.schema.commands import Command
from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.status import MachineState, MotionRef, Status
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.commands.completions import CompletionLog
from ride_machine.sim.physics import SwitchFault
from tests.rig import BAD_SESSION, Rig, known_calibration
from tests.schema.completion_samples import done_notice
from tests.service.core.storage.test_persist_failure import SlowStore

S = MachineState
C = Command


@dataclass
class Heard:
    """Every notice, with the last status published before it (to pin the order)."""

    rig: Rig

    @property
    def notices(self) -> list[tuple[Completion, Status | None]]:
        return self.rig.sink.completions

    def of(self, tid: str) -> list[Completion]:
        return [n for n, _ in self.notices if n.transaction_id == tid]

    def one(self, tid: str) -> Completion:
        found = self.of(tid)
        assert len(found) == 1, found
        return found[0]

    def refused(self, command: Command, tid: str, **payload: Any) -> Completion:
        """Send a command its checks refuse; its one notice, after the next cycle."""
        assert not self.rig.send(command, transaction_id=tid, **payload).success
        self.rig.step()
        return self.one(tid)

    def wait(self, tid: str, max_s: float = 120.0) -> Completion:
        self.rig.run_until(lambda: bool(self.of(tid)), max_s)
        self.rig.step(50)  # nothing more may come for it
        return self.one(tid)


def ending(notice: Completion) -> tuple[str, str | None, MachineState]:
    return notice.outcome, notice.code, notice.state


def estop_pulse(rig: Rig, held: int, after: int) -> None:
    """Press the E-stop for `held` cycles, then release it for `after` cycles."""
    rig.hal.press_estop()
    rig.step(held)
    rig.hal.release_estop()
    rig.step(after)


def ready() -> tuple[Rig, Heard]:
    rig = Rig(calibration=known_calibration())
    heard = Heard(rig)
    rig.home()
    return rig, heard


def test_home_ends_with_one_done_notice_published_after_its_idle_status() -> None:
    rig = Rig(calibration=known_calibration())
    heard = Heard(rig)
    assert rig.send(C.HOME, transaction_id="h1", rider="r1").success
    rig.step()
    motion = rig.sink.statuses[-1].motion
    assert motion is not None and (motion.transaction_id, motion.command) == ("h1", "Home")
    notice = heard.wait("h1")
    assert (notice.command, notice.outcome, notice.state) == ("Home", Outcome.DONE, S.IDLE)
    assert notice.code is None and notice.rider == "r1" and notice.machine_id == "m1"
    assert notice.started_at < notice.time
    before = heard.notices[-1][1]
    assert before is not None and before.state is S.IDLE and before.motion is None


def test_both_calibrations_end_done_and_the_session_ends_done_in_state_done() -> None:
    rig = Rig()
    heard = Heard(rig)
    assert rig.send(C.CALIBRATE_TILT, transaction_id="ct").success
    assert heard.wait("ct").outcome is Outcome.DONE
    assert rig.send(C.CALIBRATE_ROTATE, transaction_id="cr").success
    cr = heard.wait("cr")
    assert (cr.command, cr.outcome) == ("CalibrateRotate", Outcome.DONE)
    rig.home()
    assert rig.send(C.START, transaction_id="s1").success
    done = heard.wait("s1")
    assert (done.command, done.outcome, done.state) == ("Start", Outcome.DONE, S.DONE)
    assert heard.notices[-1][1] is not None and heard.notices[-1][1].state is S.DONE


def test_a_start_refused_by_its_checks_sends_the_warning_then_its_notice() -> None:
    rig = Rig()  # not calibrated
    heard = Heard(rig)
    notice = heard.refused(C.START, "s-nocal")
    assert (notice.outcome, notice.code) == (Outcome.REFUSED, "NOT_CALIBRATED")
    assert notice.state is S.WARNING_NEEDS_CALIBRATION
    before = heard.notices[-1][1]
    assert before is not None and before.state is S.WARNING_NEEDS_CALIBRATION

    rig = Rig(calibration=known_calibration())  # calibrated, not home
    notice = Heard(rig).refused(C.START, "s-nohome")
    assert ending(notice) == (Outcome.REFUSED, "NOT_HOME", S.WARNING_NOT_HOME)


def test_an_invalid_session_ends_fault_hw() -> None:
    _, heard = ready()
    notice = heard.refused(C.START, "bad", session=BAD_SESSION.model_dump())
    assert ending(notice) == (Outcome.FAULT_HW, "INVALID_SESSION", S.FAULT_HW)


def test_pause_and_resume_do_not_end_a_motion_and_stop_ends_it_stopped() -> None:
    rig, heard = ready()
    assert rig.send(C.START, transaction_id="s1").success
    rig.step(20)
    assert rig.send(C.PAUSE).success
    rig.step(100)
    assert rig.sink.statuses[-1].motion == rig.state_machine.action.ref()  # type: ignore[union-attr]
    assert rig.send(C.RESUME).success
    rig.step(20)
    assert heard.of("s1") == []
    assert rig.send(C.STOP, transaction_id="stop1").success
    rig.step()
    notice = heard.one("s1")
    assert (notice.outcome, notice.state, notice.reason) == (Outcome.STOPPED, S.DONE, "Stop")
    assert heard.of("stop1") == []  # Stop's reply is its completion
    assert rig.sink.statuses[-1].motion is None


def test_a_notice_is_answered_as_soon_as_the_status_it_ended_with_is_published() -> None:
    """Run 52: a Rider that heard the status IDLE after a Home and asked `done/<tid>` at once
    was told IN_PROGRESS: a loaded host had preempted the scan thread between the status's
    publication and the notice's. From the status on, the notice is answered."""
    rig = Rig(calibration=known_calibration())
    heard = Heard(rig)
    log = rig.loop.completions
    answers: list[tuple[S, object]] = []
    publish = rig.sink.publish_status

    def and_ask(status: Status) -> None:  # a Rider that heard it asks at once
        publish(status)
        answers.append((status.state, log.lookup("h1")))

    rig.sink.publish_status = and_ask  # type: ignore[method-assign]
    assert rig.send(C.HOME, transaction_id="h1").success
    notice = heard.wait("h1")
    assert answers[-1] == (S.IDLE, notice)  # not the motion still under way
    assert all(isinstance(a, MotionRef) for state, a in answers[:-1] if state is S.HOMING)


def test_a_notice_is_answered_only_with_the_status_it_ended_with() -> None:
    """A Stop serviced between two cycles ends the motion at once; until the cycle that
    publishes the status it ended with, `done/<tid>` still answers it as under way. Run 35: a
    `start --wait` on a loaded host asked for its notice in that gap, got STOPPED, then asked
    for the status and printed FAULT_ESTOP, the one before the Stop."""
    rig, heard = ready()
    log = rig.loop.completions
    assert rig.send(C.START, transaction_id="s1").success
    rig.step(30)
    estop_pulse(rig, held=5, after=1)
    assert rig.send(C.STOP).success  # as the runner services it: between two cycles
    held = log.lookup("s1")
    assert isinstance(held, MotionRef) and held.command == "Start"  # IN_PROGRESS still
    assert "s1" not in [n.transaction_id for n in log.recent()]
    assert rig.loop.published.status is not None
    assert rig.loop.published.status.state is S.FAULT_ESTOP  # what a status query answers now
    rig.step()
    notice = log.lookup("s1")
    assert isinstance(notice, Completion) and notice.outcome is Outcome.STOPPED
    assert rig.loop.published.status.state is notice.state is S.DONE
    assert heard.one("s1") == notice


def test_an_estopped_motion_that_is_resumed_ends_done() -> None:
    rig, heard = ready()
    assert rig.send(C.START, transaction_id="s1").success
    rig.step(30)
    estop_pulse(rig, held=50, after=5)
    assert heard.of("s1") == []
    assert rig.send(C.RESUME).success
    assert heard.wait("s1").outcome is Outcome.DONE


def test_home_replacing_an_estopped_session_ends_it_fault_estop() -> None:
    rig, heard = ready()
    assert rig.send(C.START, transaction_id="s1").success
    rig.step(30)
    estop_pulse(rig, held=5, after=5)
    assert rig.send(C.HOME, transaction_id="h2").success
    rig.step()
    old = heard.one("s1")
    assert ending(old) == (Outcome.FAULT_ESTOP, "ESTOP", S.FAULT_ESTOP)
    assert "replaced by Home" in old.reason
    assert heard.wait("h2").outcome is Outcome.DONE


def test_stop_after_an_estop_ends_the_motion_stopped() -> None:
    rig, heard = ready()
    assert rig.send(C.HOME, transaction_id="h2").success
    rig.step(10)
    estop_pulse(rig, held=5, after=1)
    assert rig.send(C.STOP).success
    rig.step()
    notice = heard.one("h2")
    assert notice.outcome is Outcome.STOPPED and "after an E-stop" in notice.reason


def test_a_hardware_fault_ends_fault_hw_with_its_code() -> None:
    rig = Rig(calibration=known_calibration())
    heard = Heard(rig)
    rig.hal.stick_home("rotate", SwitchFault.STUCK_OPEN)
    assert rig.send(C.HOME, transaction_id="h1").success
    notice = heard.wait("h1")
    assert ending(notice) == (Outcome.FAULT_HW, "ROTATE_HOME_TIMEOUT", S.FAULT_HW)


def test_a_repeated_transaction_id_acts_once_and_gets_one_notice() -> None:
    rig = Rig(calibration=known_calibration())
    heard = Heard(rig)
    first = rig.send(C.HOME, transaction_id="h1")
    assert rig.send(C.HOME, transaction_id="h1") == first
    heard.wait("h1")


def test_the_rider_loss_stop_policy_ends_the_motion_stopped() -> None:
    config = MachineConfig().with_overrides(rider_loss={"policy": "stop", "grace_s": 0.0})
    rig = Rig(config=config, calibration=known_calibration())
    heard = Heard(rig)
    rig.home()
    assert rig.send(C.START, transaction_id="s1", rider="r1").success
    rig.step(10)
    assert rig.state_machine.rider_lost(rig.clock())
    rig.step()
    notice = heard.one("s1")
    assert (notice.outcome, notice.code) == (Outcome.STOPPED, "RIDER_LOST")


def test_a_motion_still_running_at_shutdown_ends_aborted() -> None:
    rig, heard = ready()
    assert rig.send(C.START, transaction_id="s1").success
    rig.step(10)
    rig.loop.abort_motion(rig.clock(), "machine daemon is shutting down")
    assert heard.one("s1").outcome is Outcome.ABORTED
    rig.loop.abort_motion(rig.clock(), "again")
    assert len(heard.of("s1")) == 1


def test_a_calibration_that_cannot_be_saved_ends_storage_failed() -> None:
    rig = Rig()
    store = SlowStore()  # the test finishes its write with a problem
    rig.state_machine.keeper.on_calibrated = store.save
    heard = Heard(rig)
    assert rig.send(C.CALIBRATE_TILT, transaction_id="ct").success
    rig.run_until(lambda: bool(store.tickets))
    rig.step(20)
    assert heard.of("ct") == [] and rig.state is S.CALIBRATING  # the disk has not answered
    store.tickets[0].finish("calibration not saved to /x (No space left on device)")
    rig.step()
    notice = heard.one("ct")
    assert (notice.outcome, notice.code) == (Outcome.STORAGE_FAILED, "STORAGE_FAILED")
    assert "No space left" in notice.reason and notice.state is not S.CALIBRATING


def test_the_log_knows_notices_the_motion_under_way_and_forgets_the_oldest() -> None:
    log = CompletionLog(capacity=2)
    ref = MotionRef(transaction_id="a", command="Home", started_at=1.0)
    log.set_active(ref)
    assert log.lookup("a") == ref and log.lookup("zz") is None

    for tid in ("a", "b", "c"):
        log.record(done_notice(tid, "Home", S.IDLE))
    assert log.lookup("a") is None  # forgotten (and no longer under way)
    assert [n.transaction_id for n in log.recent()] == ["b", "c"]


def test_a_full_window_of_notices_is_kept_small_and_read_back_as_it_was() -> None:
    """4,096 notices held 6.1 MiB as models (a riding daemon's growth, bench.rss_soak), 1.5 MiB
    as their msgpack bytes."""
    log = CompletionLog(capacity=4096)
    rider = "bay1/" + "ab" * 16

    def notice(i: int) -> Completion:
        return done_notice(f"rider-{i:012x}-{i}", rider=rider, started_at=1.5e9 + i, took_s=0.25)

    first = notice(0)
    tracemalloc.start()
    try:
        log.record(first)
        for i in range(1, 4096):
            log.record(notice(i))
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held < 2.5 * 2**20, f"{held / 2**20:.1f} MiB for a full window"
    assert log.lookup(first.transaction_id) == first
    assert log.recent()[0] == first and len(log.recent()) == 4096


def test_a_newer_outcome_is_kept_as_its_string() -> None:
    raw = notice_json(outcome="PARTLY_DONE")
    assert Completion.model_validate(raw).outcome == "PARTLY_DONE"
    assert Completion.model_validate(notice_json(outcome="DONE")).outcome is Outcome.DONE


def notice_json(**over: object) -> dict[str, object]:
    base: dict[str, object] = {
        "machine_id": "m1",
        "transaction_id": "t",
        "command": "Home",
        "outcome": "DONE",
        "state": "IDLE",
        "started_at": 1.0,
        "time": 2.0,
    }
    return {**base, **over}
