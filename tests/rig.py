"""A machine on the simulator with a fake clock: thousands of cycles in milliseconds."""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any
from unittest.mock import patch

from ride_machine.hal.base import Outputs
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import CalibrationRecord
from ride_machine.schema.commands import Command, Reply, Session, StartRequest, TiltStep
from ride_machine.schema.commands import CommandRequest as Req
from ride_machine.schema.completion import Completion
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import MachineState, Status
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.history.events import EventSink
from ride_machine.service.core.motion.devices import Calibration
from ride_machine.service.core.scan.machine import Machine
from ride_machine.service.core.scan.port import LoopPort
from ride_machine.service.core.scan.tasks import PendingCommand
from ride_machine.service.core.scan.watchdog import GuardedHal
from ride_machine.service.core.statemachine import Transition
from ride_machine.service.core.storage.persist import CalibrationStore
from ride_machine.sim.hal import SimHal
from ride_machine.sim.settings import PhysicsParams


class FakeClock:
    """Time that moves only when told to."""

    def __init__(self, start: float = 1000.0) -> None:
        self.t = start

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += dt
        return self.t


class RecordingSink:
    """Keeps everything the loop publishes; each notice with the status published before it."""

    def __init__(self) -> None:
        self.statuses: list[Status] = []
        self.io: list[IoValue] = []
        self.axes: list[AxisRecord] = []
        self.completions: list[tuple[Completion, Status | None]] = []
        self.calibrations: list[CalibrationRecord] = []

    def publish_status(self, status: Status) -> None:
        self.statuses.append(status)

    def publish_io(self, points: list[IoValue]) -> None:
        self.io.extend(points)

    def publish_axes(self, records: list[AxisRecord]) -> None:
        self.axes.extend(records)

    def publish_completion(self, notice: Completion) -> None:
        self.completions.append((notice, self.statuses[-1] if self.statuses else None))

    def publish_calibration(self, record: CalibrationRecord) -> None:
        self.calibrations.append(record)


class MemoryStore:
    """A calibration store kept in memory: a machine that powers up already calibrated."""

    def __init__(self, calibration: Calibration | None = None) -> None:
        self.calibration = calibration or Calibration()
        self.saved: list[Calibration] = []

    def load(self) -> tuple[Calibration, str | None]:
        return self.calibration, None

    def save(self, cal: Calibration) -> None:
        self.calibration = cal
        self.saved.append(cal)


_ids = itertools.count(1)


class Rig:
    """A simulated ride: `send()` a command, `run_until()` a condition, then inspect it."""

    def __init__(
        self,
        config: MachineConfig | None = None,
        data_dir: Path | None = None,
        physics: PhysicsParams | None = None,
        calibration: Calibration | None = None,
        clock: FakeClock | None = None,
        events: EventSink | None = None,
        *,
        guarded: bool = False,
        quiet_cycles: bool = True,
    ) -> None:
        """`calibration` powers the machine up with that calibration already stored;
        `guarded` puts the watchdog's latch (`self.guard`) between the loop and the HAL;
        `quiet_cycles=False` runs every cycle in full (`ScanLoop.quiet_cycles`)."""
        if data_dir is not None and calibration is not None:
            raise ValueError("give data_dir or calibration, not both")
        self.config = config or MachineConfig()
        self.clock = clock or FakeClock()
        self.period = self.config.loop.period_s
        physics = physics or PhysicsParams.model_validate(self.config.hal.sim)
        self.hal = SimHal(self.clock, self.config.hal.iomap, physics, self.clock.advance)
        self.sink = RecordingSink()
        self.transitions: list[Transition] = []
        self.store = CalibrationStore(data_dir, clock=self.clock) if data_dir else None
        self.memory = MemoryStore(calibration) if calibration is not None else None
        self.guard = GuardedHal(self.hal) if guarded else None
        self.machine = Machine(
            self.config,
            self.guard or self.hal,
            now=self.clock(),
            store=self.store or self.memory,  # type: ignore[arg-type]
            sink=self.sink,
            on_transition=self.transitions.append,
            events=events,
            guard=self.guard,
            clock=self.clock,  # a scan stall before the write moves it (sim/hal.py)
        )
        self.loop = self.machine.loop
        self.port = LoopPort(self.loop, self.clock)
        """The loop as the bus sees it (a command between cycles, as from a Zenoh callback)."""
        self.loop.quiet_cycles = quiet_cycles
        self.loop.verify_quiet = True  # each quiet cycle checked against a fresh snapshot
        self.state_machine = self.machine.state_machine
        self.replies: list[Reply] = []
        self.step()

    @property
    def state(self) -> MachineState:
        return self.state_machine.state

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.clock.advance(self.period)
            self.loop.step(self.clock())

    def step_late(self, late_s: float) -> None:
        """One cycle whose output write comes `late_s` late: the scan thread preempted after it
        read and decided (a loaded host), so the old outputs run on meanwhile."""
        write = self.hal.scan_outputs

        def late(outputs: Outputs) -> None:
            self.clock.advance(late_s)
            write(outputs)

        with patch.object(self.hal, "scan_outputs", late):
            self.step()

    def send(self, command: Command, **payload: Any) -> Reply:
        """Queue a command the way the bus does and let the runner service it between cycles."""
        payload.setdefault("transaction_id", f"t{next(_ids)}")
        model = StartRequest if command is Command.START else Req
        got: list[Reply] = []
        self.loop.inbox.put(PendingCommand(command, model.model_validate(payload), got.append))
        self.loop.service_inbox(self.clock())
        self.loop.recorder.release()  # as the cycle that serviced it does, outputs written
        assert len(got) == 1, f"{command} got {len(got)} replies"
        self.replies.append(got[0])
        return got[0]

    def run_until(self, pred: Callable[[], bool], max_s: float = 120.0) -> float:
        """Step until `pred()`; returns the simulated seconds it took, fails after `max_s`."""
        start = self.clock()
        limit = int(max_s / self.period) + 1
        for _ in range(limit):
            if pred():
                return self.clock() - start
            self.step()
        raise AssertionError(f"condition not met within {max_s} s; state {self.state}")

    def run_to_state(self, *states: MachineState, max_s: float = 120.0) -> float:
        return self.run_until(lambda: self.state in states, max_s)

    def rotate_estimate_error_deg(self) -> float:
        """How far the machine's rotate angle lies from the world's, either way round."""
        angle = self.loop.axes.rotate.angle
        assert angle is not None, "the machine has no rotate angle"
        return abs((angle - self.hal.world.rotate_deg + 180) % 360 - 180)

    def relays_on(self) -> bool:
        return self.hal.outputs.any_on()

    def calibrate(self) -> None:
        """CalibrateTilt then CalibrateRotate, each to completion."""
        for cmd in (Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE):
            assert self.send(cmd).success
            self.run_until(lambda: self.state is not MachineState.CALIBRATING)
        assert self.state_machine.calibration.complete, self.state

    def home(self) -> None:
        assert self.send(Command.HOME).success
        self.run_to_state(MachineState.IDLE, MachineState.FAULT_HW, MachineState.WARNING_NOT_HOME)
        assert self.state is MachineState.IDLE, self.state_machine.fault

    def ready(self) -> Rig:
        """Calibrated and homed: IDLE, ready to Start."""
        self.calibrate()
        self.home()
        return self


@functools.cache
def known_calibration() -> Calibration:
    """What a real calibration run on the default simulator finds (run once per test session)."""
    rig = Rig()
    rig.calibrate()
    return rig.state_machine.calibration


WIDE_SCALE = {
    "gain_min_counts_per_deg": 5.0,
    "gain_max_counts_per_deg": 500.0,
    "zero_min_counts": -1_000_000.0,
    "zero_max_counts": 1_000_000.0,
}
UNCOMMISSIONED = MachineConfig().with_overrides(tilt=WIDE_SCALE)
"""A machine whose tilt sensor scale is as wide as the config allows (never commissioned
narrower): the witnesses alone judge a calibration. Tests of the witnesses use it, so that the
scale (service/core/motion/scale.py) does not refuse their wrong values first."""


BAD_SESSION = Session(name="too-steep", steps=[TiltStep(degrees=80.0)])
"""Outside the default machine's tilt range (0..60°): Start with it ends in FAULT_HW."""


def rig_in(state: MachineState, *, estop_held: bool = True) -> Rig:
    """A rig driven into `state` the way an operator would get there.

    Calibration-free states start from a bare machine; the others from a calibrated one.
    `estop_held=False` releases the E-stop again after entering FAULT_ESTOP.
    """
    S = MachineState
    if state in (S.WARNING_NEEDS_CALIBRATION, S.CALIBRATING):
        rig = Rig()
        if state is S.CALIBRATING:
            assert rig.send(Command.CALIBRATE_TILT).success
            rig.step(5)
    else:
        rig = Rig(calibration=known_calibration())
        if state is S.HOMING:
            assert rig.send(Command.HOME).success
            rig.step(5)
        elif state is not S.WARNING_NOT_HOME:
            rig.home()
    if state in (S.RUNNING, S.PAUSED, S.DONE):
        assert rig.send(Command.START).success
        rig.step(5)
        if state is S.PAUSED:
            assert rig.send(Command.PAUSE).success
            rig.step()
        elif state is S.DONE:
            rig.run_to_state(S.DONE, S.FAULT_HW)
    elif state is S.FAULT_ESTOP:
        rig.hal.press_estop()
        rig.step()
        if not estop_held:
            rig.hal.release_estop()
            rig.step()
    elif state is S.FAULT_HW:
        # A hardware fault as a ride meets one (it drops the references): a tilt drive that
        # does not move, repaired once the machine has faulted, so it can be homed again. A
        # Start refused for its session moves nothing and keeps them (issue 58, point 8).
        rig.hal.stall("tilt")
        assert rig.send(Command.START).success
        rig.run_to_state(S.FAULT_HW)
        rig.hal.clear_faults()
    assert rig.state is state, (state, rig.state, rig.state_machine.fault)
    return rig
