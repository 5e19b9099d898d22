"""The watchdog catches a scan thread that stops cycling and forces the outputs safe."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from ride_machine.schema.commands import Command, CommandRequest
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import LoopSection, MachineConfig
from ride_machine.service.core.scan.loop import ScanLoop
from ride_machine.service.core.scan.machine import Machine
from ride_machine.service.core.scan.runner import RealtimeRunner
from ride_machine.service.core.scan.tasks import LoopCall, PendingCommand
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.scan.watchdog import ARM_AFTER_CYCLES, GuardedHal, Watchdog
from ride_machine.sim.hal import SimHal
from tests.rig import Rig

WAIT_S = 10.0


@pytest.mark.hazard("H01")
def test_latched_hal_writes_only_safe_outputs() -> None:
    rig = Rig()
    guard = GuardedHal(rig.hal)
    on = rig.hal.outputs
    on.ro = dict.fromkeys(on.ro, True)
    guard.scan_outputs(on)
    assert rig.hal.outputs.any_on()
    guard.latch_safe()
    assert not rig.hal.outputs.any_on()
    guard.scan_outputs(on)  # a stale write after the trip
    assert not rig.hal.outputs.any_on()
    guard.unlatch()
    guard.scan_outputs(on)
    assert rig.hal.outputs.any_on()


@pytest.mark.hazard("H01")
def test_loop_takes_the_watchdog_fault_before_writing_again() -> None:
    rig = Rig(guarded=True)
    guard = rig.guard
    assert guard is not None
    assert rig.send(Command.HOME).success
    rig.step(3)
    assert rig.relays_on()
    guard.latch_safe(1.3043)
    assert not rig.relays_on()
    rig.step()
    assert rig.state is MachineState.FAULT_HW
    assert (
        rig.state_machine.fault is not None and rig.state_machine.fault.code is FaultCode.WATCHDOG
    )
    # The status after the trip keeps saying how long (the watchdog thread's first one does).
    assert rig.state_machine.fault.message.startswith("scan loop stalled 1304 ms;")
    assert not guard.latched
    rig.step(50)
    assert not rig.relays_on()


@pytest.mark.parametrize("path", ["callback", "queue"])
def test_a_command_between_cycles_finds_the_watchdog_fault_first(path: str) -> None:
    """The watchdog publishes FAULT_HW from its own thread; a Home sent on that status before
    the next cycle — run from a Zenoh callback or from the runner's queue — is judged against
    the fault (accepted), not the interrupted homing."""
    rig = Rig(guarded=True)
    guard = rig.guard
    assert guard is not None
    assert rig.send(Command.HOME).success
    rig.step(3)
    assert rig.state is MachineState.HOMING
    guard.latch_safe()
    if path == "callback":
        request = CommandRequest.model_validate({"transaction_id": "after-trip"})
        reply = rig.port.execute(Command.HOME, request, sender=None, timeout=1.0)
    else:
        reply = rig.send(Command.HOME)
    assert reply is not None and reply.success, reply
    assert rig.state_machine.fault is None and rig.state is MachineState.HOMING
    assert not guard.latched
    faults = [t for t in rig.transitions if t.new is MachineState.FAULT_HW]
    assert len(faults) == 1 and "watchdog" in faults[0].reason


class Threaded:
    """A machine on the simulator run by a real runner thread, its watchdog wired as the daemon
    wires it; `stalled` holds what each trip measured, `tripped` is set by the first."""

    def __init__(self) -> None:
        self.config = MachineConfig().with_overrides(loop={"period_s": 0.005})
        period = self.config.loop.period_s
        self.hal = SimHal(time.monotonic, self.config.hal.iomap, self.config.hal.sim)
        guard = GuardedHal(self.hal)
        self.machine = Machine(
            self.config, guard, now=time.monotonic(), on_transition=None, guard=guard
        )
        self.loop: ScanLoop = self.machine.loop
        self.tripped = threading.Event()
        self.stalled: list[float] = []
        self.dog = Watchdog(guard, 3 * period, on_trip=self.on_trip)
        self.runner = RealtimeRunner(self.loop, period, CycleStats(period), watchdog=self.dog)

    def on_trip(self, stalled_s: float) -> None:
        self.stalled.append(stalled_s)
        self.tripped.set()

    def seen(self, condition: Callable[[ScanLoop], bool]) -> threading.Event:
        """An event the scan thread sets in the first cycle where `condition` holds."""
        seen = threading.Event()

        def check(lp: ScanLoop, now: float) -> None:
            if condition(lp):
                seen.set()
            else:
                lp.inbox.put(LoopCall(check))

        self.loop.inbox.put(LoopCall(check))
        return seen


@pytest.mark.hazard("H01", "H04")
def test_stuck_loop_is_caught_by_the_watchdog_thread() -> None:
    """A real runner thread blocked inside a cycle: the watchdog trips and outputs drop."""
    threaded = Threaded()
    hal, loop, runner, dog = threaded.hal, threaded.loop, threaded.runner, threaded.dog
    replies: list[object] = []
    loop.inbox.put(
        PendingCommand(Command.HOME, CommandRequest(transaction_id="h1"), replies.append)
    )
    release = threading.Event()

    def block(lp: ScanLoop, now: float) -> None:
        release.wait(WAIT_S)  # a controller stuck in a blocking call

    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    dog.start()
    try:
        # relays on, and the watchdog armed
        moving = threaded.seen(
            lambda lp: hal.outputs.any_on() and runner.pulse.count >= ARM_AFTER_CYCLES
        )
        assert moving.wait(WAIT_S), "homing never energised a relay"
        loop.inbox.put(LoopCall(block))
        assert threaded.tripped.wait(WAIT_S), "watchdog did not trip"
        assert not hal.outputs.any_on()
        assert threaded.stalled[0] >= 3 * threaded.config.loop.period_s
    finally:
        release.set()
        seen = threaded.seen(lambda lp: lp.state_machine.state is MachineState.FAULT_HW)
        got_fault = seen.wait(WAIT_S)
        dog.stop()
        runner.stop()
        thread.join(WAIT_S)
    assert got_fault
    assert threaded.machine.state_machine.fault is not None
    assert threaded.machine.state_machine.fault.code is FaultCode.WATCHDOG
    assert (
        f"stalled {threaded.stalled[0] * 1000:.0f} ms"
        in threaded.machine.state_machine.fault.message
    )
    assert not hal.outputs.any_on()
    assert not thread.is_alive()


def limit(period_s: float, periods: int, min_s: float) -> float:
    """The watchdog limit as the config works it out (the one place it is)."""
    return LoopSection(
        period_s=period_s, watchdog_periods=periods, watchdog_min_s=min_s
    ).watchdog_limit_s


def test_watchdog_limit_is_periods_with_a_floor() -> None:
    assert limit(0.010, 3, 0.02) == pytest.approx(0.030)
    assert limit(0.001, 3, 0.02) == pytest.approx(0.020)
    assert limit(0.001, 3, 0.0) == pytest.approx(0.003)


def test_a_healthy_loop_is_checked_once_per_limit_after_its_latest_beat() -> None:
    guard = GuardedHal(Rig().hal)
    dog = Watchdog(guard, limit(0.010, 3, 0.02))
    # Limit 30 ms, checks every 10 ms: the next check 40 ms after the beat (one wake-up).
    assert dog.next_check(beat_at=5.000, now=5.004) == pytest.approx(0.036)  # 5.040 - 5.004
    # Never sooner than the plain check interval (limit / 3), even for an old beat.
    assert dog.next_check(beat_at=5.000, now=5.035) == pytest.approx(0.010)
