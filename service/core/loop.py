"""The scan loop: read inputs → E-stop → commands → update → write outputs → publish.

`ScanLoop.step(now)` is a pure function of (inputs, queued commands, now); the real-time runner
in `service/core/runner.py` calls it on absolute deadlines. Machine state has one writer at a time,
`ScanLoop.lock`: the scan thread holds it for each cycle; Zenoh's thread takes it, if free, to run
a command between cycles, and the bus's deferred thread waits for it (`execute_between_cycles`);
other threads put work into the `Inbox`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, TypeVar

from pydantic import BaseModel

from hal.base import Hal
from schema.axes import AxisRecord
from schema.calibration import (
    CalibrationRecord,
    RotateCalibrationValues,
    TiltCalibrationValues,
)
from schema.commands import Command, CommandRequest, Reply
from schema.completion import Completion
from schema.errors import Error
from schema.events import RiderEvent
from schema.io import IoValue
from schema.status import Fault, FaultCode, Status
from service.config.model import MachineConfig
from service.core.axes import AxisTracker
from service.core.completions import CompletionLog
from service.core.control import ControlAPI
from service.core.devices import Calibration, Devices
from service.core.events import EventRecorder, NullEventSink, hold_limit
from service.core.io import IoChanges, IoPoints, ProcessImage
from service.core.transactions import TransactionLog
from service.core.watchdog import GuardedHal
from service.errors import Busy, NotAvailable

log = logging.getLogger("machine")

W = TypeVar("W", bound=BaseModel)


class LoopSink(Protocol):
    """Where the loop's publications go (the Zenoh bus, or a list in tests)."""

    def publish_status(self, status: Status) -> None: ...

    def publish_io(self, points: list[IoValue]) -> None: ...

    def publish_axes(self, records: list[AxisRecord]) -> None: ...


class RiderBeats(Protocol):
    """When each Rider's heartbeat last arrived, on the loop's clock (the bus records them)."""

    def last_heartbeat(self, rider: str) -> float | None: ...


class NullSink:
    """Publishes nothing."""

    def publish_status(self, status: Status) -> None:
        pass

    def publish_io(self, points: list[IoValue]) -> None:
        pass

    def publish_axes(self, records: list[AxisRecord]) -> None:
        pass


SinkFactory = Callable[["ScanLoop"], LoopSink]
"""Makes the sink from the loop it serves (the Zenoh bus answers queries from the loop too)."""


def _sink(given: LoopSink | SinkFactory, loop: ScanLoop) -> LoopSink:
    return given(loop) if callable(given) else given


class Task(Protocol):
    """Work for the scan thread: `run` there, or `reject` if it can never run."""

    def run(self, loop: ScanLoop, now: float) -> None: ...

    def reject(self, error: Error) -> None: ...


@dataclass
class PendingCommand:
    """A decoded command waiting for the scan thread; `respond` sends its one reply."""

    command: Command
    request: CommandRequest
    respond: Callable[[Reply], None]
    sender: str | None = None
    """The sending session's id, for the event history (the Rider attaches it)."""

    def run(self, loop: ScanLoop, now: float) -> None:
        self.respond(loop.execute(self.command, self.request, now, sender=self.sender))

    def reject(self, error: Error) -> None:
        self.respond(
            Reply.failure(
                error,
                transaction_id=self.request.transaction_id,
                command=self.command.value,
                timecode=time.time(),
                request_timecode=self.request.timecode,
            )
        )


@dataclass
class LoopCall:
    """Any other work for the scan thread (a parameter write, a sim fault, a rider loss)."""

    fn: Callable[[ScanLoop, float], None]
    on_reject: Callable[[Error], None] | None = None

    def run(self, loop: ScanLoop, now: float) -> None:
        self.fn(loop, now)

    def reject(self, error: Error) -> None:
        if self.on_reject is not None:
            self.on_reject(error)


class Wake:
    """`threading.Event`'s set/clear/wait on one raw lock, released while set.

    The runner waits on it every cycle: a wait is one lock acquire, where `Event.wait` builds
    a `Condition` waiter each time (~40 µs of a cold cycle on a 2-core host, bench.cost).
    """

    def __init__(self) -> None:
        self._gate = threading.Lock()
        self._gate.acquire()  # held while clear: a wait blocks on it
        self._guard = threading.Lock()
        self.flag = False
        """`is_set()` as a plain attribute, for the scan loop's every cycle (no call)."""

    def is_set(self) -> bool:
        return self.flag

    def set(self) -> None:
        with self._guard:
            if not self.flag:
                self.flag = True
                self._gate.release()

    def clear(self) -> None:
        with self._guard:
            if self.flag:
                self.flag = False
                self._gate.acquire()  # a waiter passing through releases it at once

    def wait(self, timeout: float) -> bool:
        """True once set (it stays set), False after `timeout` seconds."""
        if not self._gate.acquire(True, timeout):
            return False
        self._gate.release()
        return True


class Inbox:
    """Thread-safe queue into the scan thread; `put` wakes the runner so replies are prompt."""

    def __init__(self, capacity: int = 1024) -> None:
        self.capacity = capacity
        self._items: deque[Task] = deque()
        self._lock = threading.Lock()
        self.wake = Wake()
        self.closed = False

    def put(self, task: Task) -> bool:
        """Queue a task; False (and nothing queued) when full or closed."""
        with self._lock:
            if self.closed or len(self._items) >= self.capacity:
                return False
            self._items.append(task)
        self.wake.set()
        return True

    def take(self, limit: int) -> list[Task]:
        if not self._items and not self.wake.flag:
            return []  # the common case, every cycle: no lock
        with self._lock:
            n = min(limit, len(self._items))
            out = [self._items.popleft() for _ in range(n)]
            if not self._items:
                self.wake.clear()
        return out

    def close(self) -> list[Task]:
        """Refuse further tasks and hand back the ones never run."""
        with self._lock:
            self.closed = True
            out = list(self._items)
            self._items.clear()
        return out

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class Published:
    """The latest records, readable from any thread (each is replaced, never mutated)."""

    status: Status | None = None
    calibration: CalibrationRecord | None = None
    io: dict[str, IoValue] = field(default_factory=dict)
    axes: dict[str, AxisRecord] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class _Rest:
    """What a full cycle that left the machine at rest depended on (`ScanLoop._at_rest`)."""

    key: tuple[object, ...]
    di: dict[str, bool]
    ai: dict[str, int]
    commands: int
    tasks: int
    watched: bool
    """A Rider controls and heartbeats are watched: the deadman runs in quiet cycles too.
    Without one it has nothing to judge until a command names a controller (a full cycle)."""


class ScanLoop:
    """One scan cycle per `step(now)`; commands between cycles with `service_inbox(now)`."""

    def __init__(
        self,
        hal: Hal,
        control: ControlAPI,
        *,
        sink: LoopSink | SinkFactory | None = None,
        inbox: Inbox | None = None,
        started_at: float = 0.0,
        guard: GuardedHal | None = None,
        recorder: EventRecorder | None = None,
    ) -> None:
        """`guard`: the watchdog's HAL wrapper, whose latch this loop turns into a fault."""
        self.hal = hal
        self.guard = guard
        self.control = control
        self.live = control.live
        config = self.live.current
        self.devices: Devices = control.devices
        self.points: IoPoints = self.devices.points
        self.image: ProcessImage = self.points.image
        self.beats: RiderBeats | None = None
        """Set by the bus: without it (an in-process rig) only the Rider's token is watched."""
        self.inbox = inbox or Inbox(config.bus.inbox_capacity)
        self.transactions = TransactionLog(config.bus.transaction_window)
        self.completions = CompletionLog(config.bus.transaction_window)
        """Recent completion notices by transaction id (the bus answers `done/<id>` from it)."""
        self.completion_listeners: list[Callable[[Completion], None]] = []
        """Called on the scan thread with each notice, after the status it ends with is
        published (the bus publishes it; the event history may record it). Never block."""
        self._unpublished: list[Completion] = []
        self.calibration_listeners: list[Callable[[CalibrationRecord], None]] = []
        """Called on the scan thread with the calibration record whenever it changes."""
        self._calibration_seen: object = None
        self._active_tid: str | None = None
        self.axes = AxisTracker(self.devices, self.live)
        self.published = Published()
        self.recorder = recorder or EventRecorder(NullEventSink(), wall_offset=control.wall_offset)
        self.recorder.hold_limit = hold_limit(config.loop.period_s)
        self.cycle = 0
        self.commands_handled = 0
        self.started_at = started_at
        self.wall_offset = control.wall_offset
        self._status_key: tuple[object, ...] | None = None
        self._status_due = 0.0
        self._seq = 0
        self.io_changes = IoChanges(self.points)
        self._max_tasks = config.loop.max_commands_per_cycle
        self.lock = threading.Lock()
        """One writer at a time: held by the runner for a cycle (and for queued tasks between
        cycles), and by the bus running a command between cycles."""
        self.tasks_run = 0
        """Inbox tasks run (between cycles and within them)."""
        self.quiet_cycles = True
        """Skip the work of a cycle that would change nothing (see `_at_rest`); False runs
        every cycle in full (the tests compare the two)."""
        self.quiet = 0
        """Quiet cycles run."""
        self._rest: _Rest | None = None
        self._commands_seen = self._tasks_seen = 0
        self.clock: Callable[[], float] | None = None
        """The clock `now` is read from, when it is a real one: the output write is stamped on
        it, so the rotate's dead reckoning counts the time a cycle took from its input scan to
        its relays (docs/homing.md). None: outputs are written at `now` (a fake clock)."""
        self.sink: LoopSink = NullSink() if sink is None else _sink(sink, self)

    @property
    def config(self) -> MachineConfig:
        """The running config (online parameters change it at a cycle boundary)."""
        return self.live.current

    # ------------------------------------------------------------------------------ cycle
    def step(self, now: float) -> None:
        """One scan cycle, in the design's order."""
        self.cycle += 1
        self.recorder.cycle = self.cycle
        live = self.live
        if live.offered is not live.current:
            live.take()  # online parameter writes take effect here, between cycles
        inputs = self.image.inputs = self.hal.scan_inputs()
        rest, self._rest = self._rest, None
        guard = self.guard
        # Everything but the control state (taken after the deadman) as at `rest`. Written
        # out here, where every idle cycle runs it: after a 10 ms sleep each Python call
        # costs microseconds of cold caches (BENCHMARKS.md section 5).
        if (
            rest is not None
            and inputs.di == rest.di
            and inputs.ai == rest.ai
            and now < self._status_due  # the status heartbeat is a full cycle
            and self.commands_handled == rest.commands
            and self.tasks_run == rest.tasks
            and not self.inbox.wake.flag  # set whenever something is queued
            and not any(self.image.outputs.ro.values())
            and (guard is None or not guard.latched)
        ):
            # No watchdog latch, no E-stop, nothing queued: the cycle goes on at the deadman.
            if rest.watched:
                self._supervise(now)
            if self.control.rest_key() == rest.key:
                # Quiet: what a full cycle does at rest, without the work that finds nothing.
                self._rest = rest
                self.hal.scan_outputs(self.image.outputs)
                self.axes.tick(now)
                self.quiet += 1
            else:
                self._rest_of_cycle(now)
            return
        self._take_watchdog_trip(now)
        if self.devices.safety.is_estop_active():
            # Same cycle the input is seen: state, controllers and outputs, before anything else.
            self.control.on_estop(now)
            self.go_safe()
            self._observe(now)
            self.service_inbox(now)  # commands are refused with ESTOP_ACTIVE, checks answered
            self._publish(now)
            return
        self.service_inbox(now)
        self._supervise(now)
        self._rest_of_cycle(now)

    def _rest_of_cycle(self, now: float) -> None:
        """After the deadman: the control acts, outputs are written, changes recorded and
        published; then whether the next cycles may be quiet ones."""
        self.control.update(now)
        self.hal.scan_outputs(self.image.outputs)
        written = now if self.clock is None else self.clock()
        # The events and log lines of commands answered since the last cycle, outputs written.
        self.recorder.release()
        self._observe(now)
        self._publish(now, written)
        commands, tasks = self.commands_handled, self.tasks_run
        if self.quiet_cycles and commands == self._commands_seen and tasks == self._tasks_seen:
            self._rest = self._at_rest()
        # else: commands or tasks came since the last full cycle, and more may follow (a
        # stream makes every cycle a full one): the next cycle without any looks again.
        self._commands_seen, self._tasks_seen = commands, tasks

    # ----------------------------------------------------------------------- quiet cycles
    # An idle machine's cycle changes nothing: the same inputs, no controller, nothing queued.
    # After a full cycle that leaves the machine at such a rest, `_at_rest` notes what it
    # depended on; a later cycle whose inputs, commands, queued tasks, timers and control
    # state (`ControlAPI.rest_key`) all match it is quiet: it still scans the inputs, runs
    # the deadman and writes the outputs, and skips `update`, the event history's compare
    # and the publication work, whose results it knows (nothing). Anything else runs the
    # full cycle, which is the one definition of what a cycle does.

    def _at_rest(self) -> _Rest | None:
        """After a full cycle: what the next cycles must find to be quiet, or None when a
        repeat of this cycle could still do something (it would publish, record, move)."""
        control = self.control
        key = control.rest_key()
        if (
            key is None
            or self._unpublished
            or any(self.image.outputs.ro.values())  # `update` would switch them off
            or (self.guard is not None and self.guard.latched)
            or self.devices.safety.is_estop_active()
            or not self.axes.at_rest()
            or not self.recorder.settled(control)
        ):
            return None
        inputs = self.image.inputs
        watched = self.beats is not None and control.controller_rider is not None
        return _Rest(
            key, dict(inputs.di), dict(inputs.ai), self.commands_handled, self.tasks_run, watched
        )

    def _take_watchdog_trip(self, now: float) -> bool:
        """The watchdog forced the outputs safe while the scan thread was stalled (and has
        published FAULT_HW already): make the machine state say so before the latch lets any
        output through again, and before any command is judged against the old state."""
        if self.guard is None or not self.guard.latched:
            return False
        self.control.external_fault(
            Fault(
                code=FaultCode.WATCHDOG,
                message="scan loop stalled; the watchdog forced the outputs safe",
            ),
            now,
        )
        self.guard.unlatch()
        return True

    def _supervise(self, now: float) -> None:
        """Deadman: the controlling Rider's latest heartbeat (data from the bus) against `now`."""
        rider = self.control.controller_rider
        if self.beats is None or rider is None:
            return
        before = self.control.state
        if self.control.rider_heartbeat(self.beats.last_heartbeat(rider), now):
            policy = self.config.rider_loss.policy
            log.warning(
                "event=rider_lost rider=%s cause=heartbeat timeout_s=%g policy=%s",
                rider,
                self.config.rider_loss.timeout_s,
                policy,
            )
            acted = self.control.state is not before
            moving = acted or self.control.is_moving()  # after a stop, only `acted` tells
            event = RiderEvent(
                kind="rider_lost", rider=rider, policy=str(policy), acted=acted, mid_motion=moving
            )
            self.recorder.emit(event, now)

    def service_inbox(self, now: float) -> int:
        """Run queued tasks (bounded per call so a storm cannot stretch a cycle unboundedly)."""
        tasks = self.inbox.take(self._max_tasks)
        if tasks:
            self.tasks_run += len(tasks)  # before they run: one that raises counts too
            for task in tasks:
                task.run(self, now)
        return len(tasks)

    def execute_between_cycles(
        self,
        command: Command,
        request: CommandRequest,
        clock: Callable[[], float],
        *,
        sender: str | None = None,
        timeout: float | None,
    ) -> Reply | None:
        """Run a command on the calling thread under the loop's lock, between two cycles.

        The command sees the state the last cycle left, as a queued one would; its effect on
        outputs comes with the next cycle, which reads inputs and handles E-stop first. None
        before the first scan and after shutdown (queue it instead); a BUSY reply when the scan
        thread holds the lock longer than `timeout` (stalled). `timeout=None` never waits: None,
        and nothing run, while the scan thread holds the lock (mid-cycle).
        """
        if timeout is None:
            if not self.lock.acquire(blocking=False):
                return None
        elif not self.lock.acquire(timeout=timeout):
            return Reply.failure(
                Busy("scan loop not responding; retry later").to_error(),
                transaction_id=request.transaction_id,
                command=command.value,
                timecode=clock() + self.wall_offset,
                request_timecode=request.timecode,
            )
        try:
            if self.cycle == 0 or self.inbox.closed:
                return None
            return self.execute(command, request, clock(), sender=sender)
        finally:
            self.lock.release()

    def execute(
        self, command: Command, request: CommandRequest, now: float, *, sender: str | None = None
    ) -> Reply:
        """One command with at-most-once semantics by transaction id."""
        # Between cycles (from a Zenoh callback or the runner's queue) a Rider that saw the
        # watchdog's FAULT_HW and sent Home at once must find the machine in that fault, not
        # in the motion the stall interrupted; within a cycle `step` has taken it already.
        if self._take_watchdog_trip(now):
            self._observe(now)  # the fault and its notice, before the command's own
        self.commands_handled += 1
        stamp = now + self.wall_offset
        repeat = self.transactions.lookup(request.transaction_id, command._value_, stamp)
        if repeat is not None:
            self.recorder.command(
                self.control, command, request, repeat, now, sender=sender, repeat=True
            )
            return repeat
        reply = self.control.handle(command, request, now)
        self.transactions.record(request.transaction_id, command._value_, reply)
        # Before the reply goes out: a Rider that asks for the notice at once finds the motion.
        self._collect_completions()
        self.recorder.command(
            self.control,
            command,
            request,
            reply,
            now,
            sender=sender,
            logged=True,
        )
        return reply

    def release_records(self, timeout: float) -> None:
        """What the recorder holds for the next cycle, handed over now (a history read sees
        every command answered before it); skipped if the loop holds its lock past `timeout`."""
        if self.recorder.holding and self.lock.acquire(timeout=timeout):
            try:
                self.recorder.release()
            finally:
                self.lock.release()

    def _observe(self, now: float) -> None:
        """After the control acted: its notices into the log, its changes into the history."""
        self._collect_completions()
        self.recorder.observe(self.control, now)

    def _collect_completions(self) -> None:
        """Take the control's new notices into the log; they are published after the status."""
        notices = self.control.take_completions()
        for notice in notices:
            self.completions.record(notice)
            self.recorder.completion(notice)
        self._unpublished += notices
        motion = self.control.action
        tid = motion.transaction_id if motion is not None else None
        if tid != self._active_tid:
            self._active_tid = tid
            self.completions.set_active(motion.ref() if motion is not None else None)

    def _publish_completions(self) -> None:
        notices, self._unpublished = self._unpublished, []
        for notice in notices:
            log.info(
                "event=completion tx=%s command=%s outcome=%s code=%s state=%s reason=%r",
                notice.transaction_id,
                notice.command,
                notice.outcome,
                notice.code,
                notice.state,
                notice.reason,
            )
            for listener in self.completion_listeners:
                listener(notice)

    def abort_motion(self, now: float, why: str) -> None:
        """On shutdown (the runner has stopped): a motion still under way ends `ABORTED`."""
        self.control.abort(now, why)
        self._observe(now)
        self._publish_completions()

    def go_safe(self) -> None:
        """Outputs off in the image and at the HAL, whatever state the loop is in."""
        self.image.all_outputs_off()
        self.hal.force_all_outputs_safe()

    # ---------------------------------------------------------------------------- publish
    def _publish(self, now: float, written: float | None = None) -> None:
        """`written`: when this cycle's outputs were written (default: now, or the clock's)."""
        wall = now + self.wall_offset
        control = self.control
        fault = control.fault
        if written is None:
            written = now if self.clock is None else self.clock()
        self.axes.update(
            now,
            control.state,
            fault.axis if fault else None,
            control.calibration.rotate,
            control.motion(),
            written,
        )
        due = self.axes.due(self.cycle)
        if due:
            records = [self.axes.record(name, self.cycle, wall) for name in due]
            self.published.axes = {**self.published.axes, **{r.axis: r for r in records}}
            self.sink.publish_axes(records)
        changed = self.io_changes.since_last(self.config.bus.ai_deadband_counts, wall)
        if changed:
            self.published.io = {**self.published.io, **{p.name: p for p in changed}}
            self.sink.publish_io(changed)
        self._collect_completions()
        if control.calibration is not self._calibration_seen:
            self._calibration_seen = control.calibration
            record = calibration_record(control.calibration, self.config.machine.id, wall)
            self.published.calibration = record
            for listener in self.calibration_listeners:
                listener(record)
        key = control.status_key()
        if key != self._status_key or now >= self._status_due:
            self._status_key = key
            self._status_due = now + self.config.bus.heartbeat_s
            status = self.build_status(now)
            self.published.status = status
            self.sink.publish_status(status)
        if self._unpublished:
            self._publish_completions()  # after the status: the seed's WARNING, then DONE

    def build_status(self, now: float) -> Status:
        control = self.control
        self._seq += 1
        warnings = list(control.warnings)
        if control.rider_warning:
            warnings.append(control.rider_warning)
        if control.storage is not None:
            warnings += control.storage.warnings()
        tilt = self.devices.tilt.read_position_degrees()
        return Status(
            machine_id=self.config.machine.id,
            state=control.state,
            previous_state=control.previous_state,
            session=control.session_progress(),
            warnings=warnings,
            fault=control.fault,
            estop=control.estop_info(),
            calibrated={
                "tilt": control.calibration.tilt is not None,
                "rotate": control.calibration.rotate is not None,
            },
            homed=control.homed(),
            tilt_deg=None if tilt is None else round(tilt, 2),
            rotate_deg=None if self.axes.rotate.angle is None else round(self.axes.rotate.angle, 1),
            rider_connected=control.rider_connected,
            motion=control.action.ref() if control.action is not None else None,
            seq=self._seq,
            cycle=self.cycle,
            time=now + self.wall_offset,
            uptime_s=round(now - self.started_at, 3),
            heartbeat_s=self.config.bus.heartbeat_s,
        )

    def reject_pending(self, why: str) -> None:
        """On shutdown: every queued command still gets its one reply."""
        for task in self.inbox.close():
            task.reject(NotAvailable(why).to_error())


def calibration_record(cal: Calibration, machine_id: str, wall: float) -> CalibrationRecord:
    """The wire record of a calibration (values, how and when each axis got them)."""
    return CalibrationRecord(
        machine_id=machine_id,
        tilt=_wire(TiltCalibrationValues, cal.tilt),
        rotate=_wire(RotateCalibrationValues, cal.rotate),
        complete=cal.complete,
        time=wall,
    )


def _wire(model: type[W], values: object | None) -> W | None:
    """One axis' calibration as its wire model (the same field names); None stays None."""
    return None if values is None else model.model_validate(values, from_attributes=True)
