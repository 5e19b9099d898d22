"""The scan loop: cycle order, command servicing, publication, start-up and shutdown safety."""

from __future__ import annotations

import itertools
import threading
from pathlib import Path

import pytest

from ride_machine.hal.base import Inputs, Outputs
from ride_machine.hal.iomap import RELAY_OUTPUTS, Signal
from ride_machine.schema.commands import REQUEST_MODELS, Command, Reply
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.schema.params import ParamSet
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.inbox import Inbox, Wake
from ride_machine.service.core.scan.loop import ScanLoop
from ride_machine.service.core.scan.machine import Machine
from ride_machine.service.core.scan.tasks import LoopCall, PendingCommand
from ride_machine.service.core.storage.params import ParamRegistry
from ride_machine.service.core.storage.persist import ParamStore
from ride_machine.sim.hal import SimHal
from tests.rig import FakeClock, Rig, known_calibration, rig_in

S = MachineState
C = Command


class CallLog(SimHal):
    """The simulator, noting the order of the loop's HAL calls."""

    def __init__(self, clock: FakeClock) -> None:
        super().__init__(clock)
        self.calls: list[str] = []

    def scan_inputs(self) -> Inputs:
        self.calls.append("scan_inputs")
        return super().scan_inputs()

    def scan_outputs(self, outputs: Outputs) -> None:
        self.calls.append("scan_outputs")
        super().scan_outputs(outputs)

    def force_all_outputs_safe(self) -> None:
        self.calls.append("force_safe")
        super().force_all_outputs_safe()


def queue(loop: ScanLoop, command: Command, tid: str, replies: list[Reply]) -> None:
    request = REQUEST_MODELS[command](transaction_id=tid)
    assert loop.inbox.put(PendingCommand(command, request, replies.append))


@pytest.mark.hazard("H43")
def test_machine_makes_outputs_safe_before_anything_else() -> None:
    clock = FakeClock()
    hal = CallLog(clock)
    hal.scan_outputs(Outputs(ro=dict.fromkeys(hal.iomap.channels(RELAY_OUTPUTS), True)))
    assert hal.outputs.any_on()  # left on by a previous life
    hal.calls.clear()

    machine = Machine(MachineConfig(), hal, now=clock(), on_transition=None)

    assert hal.calls[0] == "force_safe"
    assert not hal.outputs.any_on()
    assert machine.state_machine.state is S.WARNING_NEEDS_CALIBRATION
    assert machine.state_machine.keeper.homed().tilt is False
    assert machine.state_machine.keeper.homed().rotate is False


def test_one_input_scan_and_one_output_write_per_cycle_in_order() -> None:
    clock = FakeClock()
    hal = CallLog(clock)
    machine = Machine(MachineConfig(), hal, now=clock(), on_transition=None)
    hal.calls.clear()
    for _ in range(5):
        clock.advance(0.01)
        machine.loop.step(clock())
    assert hal.calls == ["scan_inputs", "scan_outputs"] * 5
    assert machine.loop.cycle == 5


def test_estop_cycle_forces_outputs_safe_instead_of_writing_them() -> None:
    clock = FakeClock()
    hal = CallLog(clock)
    machine = Machine(MachineConfig(), hal, now=clock(), on_transition=None)
    hal.calls.clear()
    hal.press_estop()
    clock.advance(0.01)
    machine.loop.step(clock())
    assert hal.calls == ["scan_inputs", "force_safe"]


def test_a_command_queued_before_a_cycle_acts_in_that_cycle() -> None:
    rig = rig_in(S.IDLE)
    replies: list[Reply] = []
    queue(rig.loop, C.START, "q-start", replies)
    assert not rig.relays_on()
    rig.step()
    assert [r.code for r in replies] == ["RESP_START_ACCEPTED"]
    assert rig.relays_on()  # outputs of the same cycle already follow the command


def test_commands_between_cycles_take_effect_at_the_next_cycle_boundary() -> None:
    rig = rig_in(S.RUNNING)
    assert rig.relays_on()
    assert rig.send(C.PAUSE).state is S.PAUSED
    assert rig.relays_on()  # the HAL still holds the last cycle's outputs...
    rig.step()
    assert not rig.relays_on()  # ...until the next write


@pytest.mark.hazard("H47")
def test_commands_per_cycle_are_bounded_and_all_answered_in_order() -> None:
    config = MachineConfig().with_overrides(loop={"max_commands_per_cycle": 4})
    rig = Rig(config=config)
    replies: list[Reply] = []
    for i in range(10):
        queue(rig.loop, C.CHECK_HOME, f"c{i}", replies)
    rig.step()
    assert len(replies) == 4
    rig.step(2)
    assert [r.transaction_id for r in replies] == [f"c{i}" for i in range(10)]
    assert all(r.success for r in replies)
    assert rig.loop.commands_handled == 10


def test_inbox_refuses_when_full_and_after_close() -> None:
    inbox = Inbox(capacity=2)
    call = LoopCall(lambda loop, now: None)
    assert inbox.put(call)
    assert inbox.wake.is_set()
    assert inbox.put(call)
    assert not inbox.put(call)
    assert len(inbox) == 2
    assert inbox.take(10) == [call, call]
    assert not inbox.wake.is_set()
    assert inbox.close() == []
    assert not inbox.put(call)


def test_wake_is_an_event_that_stays_set_until_cleared() -> None:
    wake = Wake()
    assert not wake.is_set()
    assert not wake.wait(0.001)
    wake.set()
    wake.set()  # twice is once
    assert wake.is_set()
    assert wake.wait(0.001)
    assert wake.wait(0.001)  # a wait does not clear it
    wake.clear()
    wake.clear()
    assert not wake.is_set()
    assert not wake.wait(0.001)
    woken = threading.Event()

    def waiter() -> None:
        if wake.wait(10.0):
            woken.set()

    thread = threading.Thread(target=waiter)
    thread.start()
    wake.set()  # from another thread, while it waits
    thread.join(10.0)
    assert woken.is_set()


def test_an_empty_inbox_clears_a_stale_wake() -> None:
    inbox = Inbox()
    inbox.wake.set()  # e.g. a put whose task another take already ran
    assert inbox.take(10) == []
    assert not inbox.wake.is_set()  # or the runner would spin on it


def test_pending_commands_are_answered_on_shutdown() -> None:
    rig = Rig()
    replies: list[Reply] = []
    queue(rig.loop, C.HOME, "late-1", replies)
    queue(rig.loop, C.STOP, "late-2", replies)
    rejected: list[Error] = []
    rig.loop.inbox.put(LoopCall(lambda loop, now: None, rejected.append))

    rig.loop.reject_pending("shutting down")

    assert [r.transaction_id for r in replies] == ["late-1", "late-2"]
    assert all(r.error is not None and r.error.code is ErrorCode.NOT_AVAILABLE for r in replies)
    assert [e.message for e in rejected] == ["shutting down"]
    assert not rig.loop.inbox.put(LoopCall(lambda loop, now: None))


def test_loop_call_runs_on_the_scan_thread_between_cycles() -> None:
    rig = rig_in(S.IDLE)
    seen: list[tuple[int, float]] = []
    rig.loop.inbox.put(LoopCall(lambda loop, now: seen.append((loop.cycle, now))))
    rig.step()
    assert seen == [(rig.loop.cycle, rig.clock())]


def test_go_safe_drops_every_output_in_image_and_hal() -> None:
    rig = rig_in(S.RUNNING)
    assert rig.relays_on()
    rig.loop.go_safe()
    assert not rig.relays_on()
    assert not any(rig.loop.image.outputs.ro.values())


def test_status_is_published_on_change_and_as_heartbeat() -> None:
    rig = Rig(calibration=known_calibration())
    rig.sink.statuses.clear()
    heartbeat = rig.config.bus.heartbeat_s
    cycles = round(heartbeat / rig.period)
    rig.step(3 * cycles)
    # Nothing changes at rest: one status per heartbeat period.
    assert len(rig.sink.statuses) == pytest.approx(3, abs=1)
    seqs = [s.seq for s in rig.sink.statuses]
    assert seqs == sorted(set(seqs))

    rig.sink.statuses.clear()
    rig.send(C.HOME)
    rig.step()
    assert rig.sink.statuses[-1].state == "HOMING"
    assert rig.sink.statuses[-1].previous_state == "WARNING_NOT_HOME"


def test_status_record_fields() -> None:
    rig = rig_in(S.RUNNING)
    rig.send(C.PAUSE)
    rig.send(C.RESUME)
    rig.step()  # previous_state changed: published in this cycle
    status = rig.loop.published.status
    assert status is not None
    assert status.machine_id == rig.config.machine.id
    assert status.state == "RUNNING"
    assert status.calibrated.tilt and status.calibrated.rotate
    assert status.time == rig.clock()
    assert status.cycle == rig.loop.cycle
    assert status.uptime_s == pytest.approx(rig.clock() - rig.loop.started_at, abs=1e-6)
    assert status.tilt_deg is not None
    assert status.estop.active is False
    # Wire form: the state is the plain state name.
    assert status.model_dump(mode="json")["state"] == "RUNNING"


def test_io_is_published_on_change_only_with_an_analog_deadband() -> None:
    rig = Rig(calibration=known_calibration())
    first = {p.name for p in rig.sink.io}
    assert first == {str(s) for s in rig.config.hal.iomap.mapped()}  # everything once at start
    assert Signal.TILT_DIR in first
    rig.sink.io.clear()
    rig.step(100)
    assert rig.sink.io == []  # nothing moves, nothing published

    rig.send(C.HOME)
    rig.step()
    names = [p.name for p in rig.sink.io]
    assert Signal.TILT_RELAY in names
    rig.sink.io.clear()
    rig.step(50)
    ai = [p.value for p in rig.sink.io if p.name == Signal.TILT_POSITION]
    assert ai
    deadband = rig.config.bus.ai_deadband_counts
    assert all(abs(int(b) - int(a)) > deadband for a, b in itertools.pairwise(ai))


def test_a_narrower_deadband_publishes_an_analog_change_it_held_back() -> None:
    rig = Rig(calibration=known_calibration())
    rig.sink.io.clear()
    deadband = rig.config.bus.ai_deadband_counts
    assert deadband >= 2
    gain = rig.config.hal.sim.ai_gain_counts_per_deg
    rig.hal.world.tilt_deg += deadband / gain  # within the deadband: held back
    rig.step(5)
    assert rig.sink.io == []
    rig.state_machine.live.offer(rig.config.with_overrides(bus={"ai_deadband_counts": 0}))
    rig.step(5)  # the image has not changed since, yet the held-back value goes out once
    assert [p.name for p in rig.sink.io] == [Signal.TILT_POSITION]


def test_axis_records_while_moving_and_once_when_stopped() -> None:
    rig = rig_in(S.IDLE)
    rig.step()  # the settled record after homing's last move
    rig.sink.axes.clear()
    rig.step(20)
    assert rig.sink.axes == []
    rig.send(C.START)
    rig.step(10)
    tilt = [a for a in rig.sink.axes if a.axis == "tilt"]
    assert len(tilt) == 10
    assert all(a.pn_status & 2 for a in tilt)  # MOVING
    assert tilt[-1].velocity_cmd > 0
    rig.sink.axes.clear()
    rig.send(C.STOP)
    rig.step(10)
    stopped = [a for a in rig.sink.axes if a.axis == "tilt"]
    assert len(stopped) == 2  # the stop itself, then one settled record
    # Stopped short of its target: not moving, and (seed 002) not settled either.
    assert not any(a.pn_status & 3 for a in stopped)
    assert stopped[-1].velocity_fb == 0.0


def test_hal_error_in_a_cycle_propagates_for_the_runner_to_handle() -> None:
    rig = rig_in(S.RUNNING)

    def broken() -> Inputs:
        raise OSError("process image gone")

    rig.hal.scan_inputs = broken  # type: ignore[method-assign]
    with pytest.raises(OSError, match="process image gone"):
        rig.step()


def test_estop_publishes_drive_disabled_for_a_standing_axis() -> None:
    rig = rig_in(S.IDLE)
    rig.step(3)
    rig.sink.axes.clear()
    rig.hal.press_estop()
    rig.step()
    records = {a.axis: a for a in rig.sink.axes}
    assert set(records) == {"rotate", "tilt"}
    assert all(not a.pn_status & 4 for a in records.values())  # DRIVE_ENABLED cleared


def test_an_online_write_reaches_every_reader_at_the_next_cycle(tmp_path: Path) -> None:
    registry = ParamRegistry(MachineConfig(), ParamStore(tmp_path))
    clock = FakeClock()
    machine = Machine(registry.live, SimHal(clock), now=clock(), on_transition=None)
    loop = machine.loop
    registry.set("bus.heartbeat_s", ParamSet(transaction_id="p1", value=7.0), moving=False, now=0.0)
    registry.set(
        "rider_loss.policy", ParamSet(transaction_id="p2", value="stop"), moving=False, now=0.0
    )
    # Offered from the writer's thread; the cycle under way keeps the config it started with.
    assert loop.config.bus.heartbeat_s == machine.state_machine.live.current.bus.heartbeat_s == 1.0
    clock.advance(0.01)
    loop.step(clock())
    assert loop.config is machine.state_machine.live.current is loop.axes.config is registry.config
    assert loop.config.bus.heartbeat_s == 7.0
    assert machine.state_machine.live.current.rider_loss.policy == "stop"
