"""Quiet cycles: an idle machine's cycle skips the work that finds nothing to do, and nothing
it does differs from the full cycle.

Each test runs two rigs in lockstep, one with quiet cycles and one running every cycle in full
(`ScanLoop.quiet_cycles = False`, its simulator sensing every scan: `SimHal.still_scans`),
applies the same things to both between the same cycles, and after every cycle compares all
they did: status, IO and axis publications, events, state transitions, HAL writes and
outputs, the input image and the simulated world, replies. A test also checks that the machine
was in a quiet streak when the thing happened, so a fast path that never runs cannot pass it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from ride_machine.hal.iomap import Signal
from ride_machine.schema.calibration import CalibrationSet
from ride_machine.schema.commands import REQUEST_MODELS, Command, Reply
from ride_machine.schema.events import RiderEvent, StorageEvent
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.history.events import ListEventSink
from ride_machine.service.core.scan.loop import ScanLoop
from ride_machine.service.core.scan.tasks import LoopCall, PendingCommand
from ride_machine.sim.physics import SwitchFault
from tests.rig import Rig, known_calibration

S = MachineState
C = Command


class Beats:
    """The bus's heartbeat record as data: arrival times on the rig's clock."""

    def __init__(self) -> None:
        self.at: dict[str, float] = {}

    def last_heartbeat(self, rider: str) -> float | None:
        return self.at.get(rider)


class Twins:
    """The same machine twice: `fast` with quiet cycles, `full` without."""

    def __init__(self, data_dir: Path | None = None, **options: Any) -> None:
        """`data_dir`: each rig stores in its own directory under it."""
        self.sinks = (ListEventSink(), ListEventSink())
        dirs: tuple[Path | None, Path | None] = (None, None)
        if data_dir is not None:
            dirs = (data_dir / "full", data_dir / "fast")
            for d in dirs:
                d.mkdir()
        self.full = Rig(events=self.sinks[0], quiet_cycles=False, data_dir=dirs[0], **options)
        self.fast = Rig(events=self.sinks[1], data_dir=dirs[1], **options)
        self.full.hal.still_scans = False  # senses the simulated world every scan
        self.beats = (Beats(), Beats())
        self.full.loop.beats, self.fast.loop.beats = self.beats
        self.rigs = (self.full, self.fast)
        self.notices = (self.full.sink.completions, self.fast.sink.completions)

    def both(self, act: Callable[[Rig], object]) -> list[object]:
        """Do the same thing to both, between the same two cycles."""
        return [act(rig) for rig in self.rigs]

    def beat(self, rider: str) -> None:
        for rig, beats in zip(self.rigs, self.beats, strict=True):
            beats.at[rider] = rig.clock()

    def send(self, command: Command, tid: str, **payload: Any) -> Reply:
        full, fast = self.both(lambda rig: rig.send(command, transaction_id=tid, **payload))
        assert isinstance(full, Reply)
        assert fast == full
        return full

    def home(self, rider: str | None = None) -> None:
        """Home both, `rider` beating every 100 ms while they move."""
        assert self.send(C.HOME, "home", rider=rider).success
        for _ in range(1000):
            if self.fast.state is not S.HOMING:
                break
            if rider is not None:
                self.beat(rider)
            self.step(10)
        assert self.fast.state is S.IDLE

    def step(self, n: int = 1) -> int:
        """Step both `n` cycles, comparing after each; the quiet cycles `fast` ran."""
        before = self.fast.loop.quiet
        for _ in range(n):
            for rig in self.rigs:
                rig.step()
            self.compare()
        assert self.full.loop.quiet == 0
        return self.fast.loop.quiet - before

    def compare(self) -> None:
        full, fast = self.full, self.fast
        assert fast.loop.cycle == full.loop.cycle
        assert fast.state is full.state
        assert fast.hal.outputs == full.hal.outputs
        assert (fast.hal.scans, fast.hal.writes) == (full.hal.scans, full.hal.writes)
        a, b = fast.hal.world, full.hal.world
        assert (a.time, a.rotate_deg, a.tilt_deg) == (b.time, b.rotate_deg, b.tilt_deg)
        assert (a._frozen_raw, a._rng.getstate()) == (b._frozen_raw, b._rng.getstate())
        assert fast.loop.image.inputs == full.loop.image.inputs
        assert fast.loop.axes.samples == full.loop.axes.samples
        assert fast.loop.published == full.loop.published
        assert self.notices[1] == self.notices[0]
        for got, want in (
            (fast.sink.statuses, full.sink.statuses),
            (fast.sink.io, full.sink.io),
            (fast.sink.axes, full.sink.axes),
            (self.sinks[1].events, self.sinks[0].events),
            (fast.transitions, full.transitions),
        ):
            assert len(got) == len(want), fast.loop.cycle
            if got:
                assert got[-1] == want[-1], fast.loop.cycle

    def compare_all(self) -> None:
        full, fast = self.full, self.fast
        assert fast.sink.statuses == full.sink.statuses
        assert fast.sink.io == full.sink.io
        assert fast.sink.axes == full.sink.axes
        assert self.sinks[1].events == self.sinks[0].events
        assert fast.transitions == full.transitions
        assert fast.loop.published == full.loop.published
        assert fast.replies == full.replies


def quiet_streak(twins: Twins, cycles: int = 50) -> None:
    """Idle `cycles` cycles; the last ones must have been quiet."""
    twins.step(cycles)
    loop = twins.fast.loop
    quiet, reused = loop.quiet, twins.fast.hal.reused
    twins.step()
    assert loop.quiet == quiet + 1, "the machine was not in a quiet streak"
    assert twins.fast.hal.reused == reused + 1, "the simulator sensed a still world"


def test_a_long_idle_run_is_quiet_and_publishes_the_same() -> None:
    twins = Twins(calibration=known_calibration())
    twins.home()
    cycles = 3000  # 30 s at 10 ms: thirty status heartbeats
    quiet = twins.step(cycles)
    heartbeats = round(cycles * twins.fast.period / twins.fast.config.bus.heartbeat_s)
    assert quiet >= cycles - 2 * heartbeats - 5
    statuses = twins.fast.sink.statuses
    assert len([s for s in statuses if s.state == "IDLE"]) >= heartbeats
    twins.compare_all()


def test_a_bare_machine_at_power_up_is_quiet_too() -> None:
    twins = Twins()
    assert twins.step(500) > 400
    assert twins.fast.state is S.WARNING_NEEDS_CALIBRATION
    twins.compare_all()


@pytest.mark.parametrize(
    "inject",
    [
        lambda rig: rig.hal.stick_home("rotate", SwitchFault.STUCK_OPEN),
        lambda rig: rig.hal.stick_home("tilt", SwitchFault.STUCK_OPEN),
        lambda rig: rig.hal.set_tilt_noise(40.0),
        lambda rig: rig.hal.freeze_tilt_ai(),
        lambda rig: rig.hal.stall("rotate"),
    ],
    ids=["rotate-switch", "tilt-switch", "tilt-noise", "tilt-frozen", "stall"],
)
def test_a_sim_fault_is_seen_in_the_same_cycle(inject: Callable[[Rig], None]) -> None:
    twins = Twins(calibration=known_calibration())
    twins.home()
    quiet_streak(twins)
    twins.both(inject)
    twins.step(300)
    twins.both(lambda rig: rig.hal.clear_faults())
    twins.step(300)
    twins.compare_all()


def test_an_estop_acts_in_the_cycle_its_input_changes() -> None:
    twins = Twins(calibration=known_calibration())
    twins.home()
    quiet_streak(twins)
    twins.both(lambda rig: rig.hal.press_estop())
    twins.step()
    assert twins.fast.state is S.FAULT_ESTOP
    assert twins.fast.state_machine.estop_latched
    twins.step(200)  # held: every cycle forces the outputs safe, none of them is quiet
    twins.both(lambda rig: rig.hal.release_estop())
    twins.step(200)
    assert twins.fast.state is S.FAULT_ESTOP  # latched until a command says otherwise
    quiet_streak(twins)
    twins.send(C.RESUME, "resume")
    twins.step(200)
    twins.compare_all()
    assert twins.fast.state is S.IDLE


def test_queued_work_and_commands_between_cycles_act_as_before() -> None:
    twins = Twins(calibration=known_calibration())
    quiet_streak(twins)
    # A command queued for the cycle, a task, a command run between cycles.
    replies: tuple[list[Reply], list[Reply]] = ([], [])
    for rig, got in zip(twins.rigs, replies, strict=True):
        request = REQUEST_MODELS[C.CHECK_HOME](transaction_id="queued")
        assert rig.loop.inbox.put(PendingCommand(C.CHECK_HOME, request, got.append))
    twins.step()
    assert replies[0] == replies[1]
    assert len(replies[1]) == 1
    quiet_streak(twins)
    ran: list[int] = []

    def task(loop: ScanLoop, now: float) -> None:
        ran.append(loop.cycle)
        loop.state_machine.warnings.append("from a task")

    twins.both(lambda rig: rig.loop.inbox.put(LoopCall(task)))
    twins.step()
    assert ran == [twins.full.loop.cycle] * 2
    assert "from a task" in twins.fast.sink.statuses[-1].warnings
    quiet_streak(twins)
    twins.home()
    quiet_streak(twins)
    twins.send(C.CHECK_CALIBRATION, "check")
    twins.step(100)
    twins.compare_all()


def test_a_parameter_write_takes_effect_at_the_next_cycle() -> None:
    twins = Twins(calibration=known_calibration())
    quiet_streak(twins, 150)
    faster = twins.fast.config.with_overrides(bus={"heartbeat_s": 0.05})
    twins.both(lambda rig: rig.machine.live.offer(faster))
    count = len(twins.fast.sink.statuses)
    twins.step(100)
    # Five cycles per heartbeat from the write on (the first one due at the old heartbeat's
    # deadline, which may be up to a second away).
    assert len(twins.fast.sink.statuses) - count >= 10
    twins.compare_all()


def test_a_silent_rider_is_lost_in_the_same_cycle() -> None:
    config = MachineConfig().with_overrides(rider_loss={"timeout_s": 0.5})
    twins = Twins(config=config, calibration=known_calibration())
    twins.home(rider="r1")
    twins.step()
    # A Rider beating every 100 ms: quiet cycles in between (the beat is no change).
    quiet = 0
    for _ in range(30):
        twins.beat("r1")
        quiet += twins.step(10)
    assert quiet > 200
    assert twins.fast.state_machine.watch.connected
    twins.step(100)  # silent: lost after 0.5 s
    assert not twins.fast.state_machine.watch.connected
    lost = [e for e, _, _ in twins.sinks[1].events if isinstance(e, RiderEvent)]
    assert [e.kind for e in lost] == ["rider_lost"]
    assert twins.fast.sink.statuses[-1].rider_connected is False
    twins.beat("r1")  # back
    twins.step(50)
    assert twins.fast.state_machine.watch.connected
    twins.compare_all()


def test_a_rider_lost_with_a_grace_period_runs_its_clock() -> None:
    config = MachineConfig().with_overrides(rider_loss={"grace_s": 0.3})
    twins = Twins(config=config, calibration=known_calibration())
    twins.home(rider="r1")
    twins.beat("r1")
    quiet_streak(twins, 20)  # within its heartbeat timeout
    twins.both(lambda rig: rig.state_machine.rider_lost(rig.clock()))  # its token went
    twins.step(100)
    twins.compare_all()


def test_a_watchdog_trip_is_taken_in_the_next_cycle() -> None:
    twins = Twins(calibration=known_calibration(), guarded=True)
    twins.home()
    quiet_streak(twins)
    for rig in twins.rigs:
        assert rig.guard is not None
        rig.guard.latch_safe()
    twins.step()
    assert twins.fast.state is S.FAULT_HW
    twins.step(200)
    twins.compare_all()


def test_storage_warnings_from_another_thread_are_published_at_once(tmp_path: Path) -> None:
    twins = Twins(tmp_path)
    quiet_streak(twins)
    for rig in twins.rigs:
        assert rig.state_machine.storage is not None
        rig.state_machine.storage.failed("data_dir", "disk full")
    twins.step()
    assert any(w.startswith("STORAGE_FAILED") for w in twins.fast.sink.statuses[-1].warnings)
    assert isinstance(twins.sinks[1].events[-1][0], StorageEvent)
    quiet_streak(twins)
    twins.compare_all()


def test_a_session_moves_settles_and_goes_quiet_again() -> None:
    twins = Twins(calibration=known_calibration())
    twins.home()
    quiet_streak(twins)
    twins.send(C.START, "start")
    twins.both(lambda rig: rig.run_to_state(S.DONE))
    quiet_streak(twins)
    settled = [a for a in twins.fast.sink.axes if a.velocity_fb == 0.0]
    assert settled
    tilt = known_calibration().tilt
    assert tilt is not None
    values = CalibrationSet.model_validate(
        {
            "transaction_id": "cal",
            "tilt": {
                "offset_counts": tilt.offset_counts + 5,
                "gain_counts_per_deg": tilt.gain_counts_per_deg,
            },
        }
    )
    twins.both(
        lambda rig: rig.loop.inbox.put(
            LoopCall(lambda loop, now: loop.state_machine.enter_calibration(values, now))
        )
    )
    twins.step()
    twins.step(200)
    twins.compare_all()


def test_a_refused_start_that_changes_no_state_still_sends_its_notice() -> None:
    twins = Twins(calibration=known_calibration())  # not home: WARNING_NOT_HOME
    quiet_streak(twins)
    state = twins.fast.state
    reply = twins.send(C.START, "start")
    assert not reply.success
    assert twins.fast.state is state  # the same state, yet a notice is due
    twins.step()
    assert [n.transaction_id for n, _ in twins.notices[1]] == ["start"]
    twins.step(100)
    twins.compare_all()


def test_a_narrower_deadband_written_at_rest_publishes_the_held_back_value() -> None:
    twins = Twins(calibration=known_calibration())
    gain = twins.fast.config.hal.sim.ai_gain_counts_per_deg
    deadband = twins.fast.config.bus.ai_deadband_counts
    quiet_streak(twins)
    for rig in twins.rigs:
        rig.hal.world.tilt_deg += deadband / gain  # within the deadband: held back
    count = len(twins.fast.sink.io)
    quiet_streak(twins)
    assert len(twins.fast.sink.io) == count
    narrower = twins.fast.config.with_overrides(bus={"ai_deadband_counts": 0})
    twins.both(lambda rig: rig.machine.live.offer(narrower))
    twins.step()
    assert [p.name for p in twins.fast.sink.io[count:]] == [Signal.TILT_POSITION]
    twins.step(100)
    twins.compare_all()


def test_a_tilt_pushed_by_hand_after_a_quiet_streak_has_the_same_velocity() -> None:
    twins = Twins(calibration=known_calibration())
    twins.home()
    quiet_streak(twins, 200)
    for rig in twins.rigs:
        rig.hal.world.tilt_deg += 3.0
    twins.step()
    assert twins.fast.loop.axes.samples["tilt"].velocity_fb > 0
    twins.step(100)
    twins.compare_all()


def test_an_output_set_in_the_image_between_cycles_is_switched_off_as_before() -> None:
    twins = Twins(calibration=known_calibration())
    quiet_streak(twins)
    for rig in twins.rigs:
        rig.loop.points.rotate_relay.set(True)
    twins.step()
    assert not twins.fast.relays_on()
    twins.step(50)
    twins.compare_all()


def test_a_command_run_from_a_callback_between_cycles_is_seen_by_the_next_cycle() -> None:
    """The Zenoh callback path (`LoopPort.execute`), which queues no task."""
    twins = Twins(calibration=known_calibration())  # not home: WARNING_NOT_HOME
    quiet_streak(twins)
    replies = twins.both(
        lambda rig: rig.port.execute(
            C.START, REQUEST_MODELS[C.START](transaction_id="cb"), sender=None, timeout=1.0
        )
    )
    assert replies[0] == replies[1]
    twins.step()
    assert [n.transaction_id for n, _ in twins.notices[1]] == ["cb"]
    twins.step(100)
    twins.compare_all()


def test_a_quiet_cycle_is_checked_against_a_fresh_snapshot_of_the_machine() -> None:
    """What lets a cycle be quiet (nothing called the machine: `StateMachine.changes`) is
    checked in every test against the snapshot a full cycle would take: a change made behind
    the machine's back is caught in the next cycle, not published late or never."""
    twins = Twins(calibration=known_calibration())
    twins.home()
    quiet_streak(twins)
    fast = twins.fast
    fast.state_machine.duplicate_of = ("elsewhere",)  # not through a method: `changes` stays put
    with pytest.raises(AssertionError, match="was quiet, but"):
        fast.step(200)  # the next quiet one (a status heartbeat may come first)
    # Through the machine's own method the same change ends the quiet streak, as it should.
    twins = Twins(calibration=known_calibration())
    quiet_streak(twins)
    fast = twins.fast
    quiet = fast.loop.quiet
    fast.state_machine.duplicate_id(("elsewhere",), "me", fast.clock())
    fast.step()
    assert fast.loop.quiet == quiet
    assert fast.sink.statuses[-1].fault is not None
