"""The scan loop: read inputs → E-stop → commands → update → write outputs → publish.

`ScanLoop.step(now)` is a pure function of (inputs, queued commands, now); the real-time runner
in `service/core/runner.py` calls it on absolute deadlines. Machine state has one writer at a time,
`ScanLoop.lock`: the scan thread holds it for each cycle; other threads see the loop only through
its port (`service/core/port.py`): a command between cycles under the lock, any other work put in
the `Inbox`, the published records as one immutable value. It publishes through one sink.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from hal.base import Hal
from schema.commands import Command, CommandRequest, Reply
from schema.completion import Completion
from schema.events import ClockEvent
from schema.status import FAULT_STATES, Fault, FaultCode, Status
from service.config.model import LiveConfig, MachineConfig
from service.core.axes import AxisTracker
from service.core.devices import Devices
from service.core.events import EventRecorder, NullEventSink
from service.core.held import hold_limit
from service.core.identity import Identity
from service.core.inbox import Inbox
from service.core.io import IoPoints, ProcessImage
from service.core.publisher import Publisher
from service.core.sink import LoopSink, NullSink, Published
from service.core.statemachine import Snapshot, StateMachine
from service.core.statemachine.deadman import Heartbeats, Verdict
from service.core.tasks import rider_event
from service.core.transactions import TransactionLog
from service.core.watchdog import GuardedHal
from service.errors import Busy, NotAvailable

log = logging.getLogger("machine")


@dataclass(frozen=True, slots=True)
class _Rest:
    """What a full cycle that left the machine at rest depended on (`ScanLoop._at_rest`)."""

    snapshot: Snapshot
    changes: int
    """`StateMachine.changes` then."""
    config: MachineConfig
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
        control: StateMachine,
        *,
        sink: LoopSink | None = None,
        inbox: Inbox | None = None,
        started_at: float = 0.0,
        guard: GuardedHal | None = None,
        recorder: EventRecorder | None = None,
        beats: Heartbeats | None = None,
    ) -> None:
        """`guard`: the watchdog's HAL wrapper, whose latch this loop turns into a fault;
        `beats`: the Riders' heartbeats (the bus records them); without them (an in-process
        rig) only the controlling Rider's token is watched."""
        self.hal = hal
        self.guard = guard
        self.control = control
        self.live: LiveConfig = control.live
        config = self.live.current
        self.devices: Devices = control.devices
        self.points: IoPoints = self.devices.points
        self.image: ProcessImage = self.points.image
        self.beats = beats
        self.inbox = inbox or Inbox(config.bus.inbox_capacity)
        self.transactions = TransactionLog(config.bus.transaction_window)
        self.axes = AxisTracker(self.devices, self.live)
        self.recorder = recorder or EventRecorder(NullEventSink(), wall_offset=control.wall_offset)
        self.recorder.hold_limit = hold_limit(config.loop.period_s)
        sink = NullSink() if sink is None else sink  # the loop's one outbound channel
        parts = (control, self.axes, self.points, sink, self.recorder)
        self.publisher = Publisher(*parts, started_at=started_at)
        self.completions = self.publisher.completions
        self.started_at = started_at
        self.cycle = 0
        self.commands_handled = 0
        self._max_tasks = config.loop.max_commands_per_cycle
        self.lock = threading.Lock()
        """One writer at a time: held by the runner for a cycle (and for queued tasks between
        cycles), and by the bus running a command between cycles."""
        self.tasks_run = 0
        """Inbox tasks run (between cycles and within them)."""
        self.quiet_cycles = True
        """Skip the work of a cycle that would change nothing (see `_at_rest`); False runs
        every cycle in full (the tests compare the two)."""
        self.verify_quiet = False
        """Check each quiet cycle against a fresh snapshot of the machine, and raise if they
        differ (the tests' rig: what the cheap checks of `step` stand for, checked)."""
        self.quiet = 0
        """Quiet cycles run."""
        self._rest: _Rest | None = None
        self._commands_seen = self._tasks_seen = 0
        self._pump = self.image.iomap.charge_pump is not None
        self.clock: Callable[[], float] | None = None
        """The clock `now` is read from, when it is a real one: the output write is stamped on
        it, so the rotate's dead reckoning counts the time a cycle took from its input scan to
        its relays (docs/homing.md). None: outputs are written at `now` (a fake clock)."""

    @property
    def config(self) -> MachineConfig:
        """The running config (online parameters change it at a cycle boundary)."""
        return self.live.current

    @property
    def wall_offset(self) -> float:
        """Wall time is `now + wall_offset`: the state machine's, which every part reads."""
        return self.control.wall_offset

    def set_wall_offset(self, offset: float, now: float, *, record: bool = True) -> None:
        """The host's clock moved against the steady one: wall times from `now` on are
        `now + offset` (the runner follows the host's clock, `RealtimeRunner`). A step that
        was set (`record`) is logged and recorded; a drift followed bit by bit is not."""
        step = offset - self.control.wall_offset
        self.control.wall_offset = self.recorder.wall_offset = offset
        if record:
            log.warning("event=clock_set step_s=%.3f", step)
            self.recorder.emit(ClockEvent(step_s=round(step, 6)), now)

    @property
    def published(self) -> Published:
        """The latest records, one immutable value (`LoopPort.snapshot`)."""
        return self.publisher.published

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
        # Everything the cycle reads besides the machine itself as at `rest`. Written out
        # here, where every idle cycle runs it: after a 10 ms sleep each Python call costs
        # microseconds of cold caches (BENCHMARKS.md section 5).
        if (
            rest is not None
            and inputs.di == rest.di
            and inputs.ai == rest.ai
            and now < self.publisher.status_due  # the status heartbeat is a full cycle
            and self.commands_handled == rest.commands
            and self.tasks_run == rest.tasks
            and not self.inbox.wake.flag  # set whenever something is queued
            and not any(self.image.outputs.ro.values())
            and (guard is None or not guard.latched)
            and live.current is rest.config  # new parameters: a full cycle takes them in
        ):
            # Of the state machine only the deadman runs here; whatever acts on it counts in
            # `changes`, and of what it shows other threads change only the data dir's health.
            # So the machine is as `rest.snapshot` unless these say otherwise (`verify_quiet`
            # checks that against a fresh snapshot in the tests).
            if rest.watched:
                self._supervise(now)
            control = self.control
            storage = control.storage
            if control.changes == rest.changes and (
                storage is None or storage.version == rest.snapshot.storage
            ):
                # Quiet: what a full cycle does at rest, without the work that finds nothing.
                self._rest = rest
                self._write()
                self.axes.tick(now)
                self.quiet += 1
                if self.verify_quiet:
                    self._verify_quiet(rest)
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
            self.publisher.publish(now, self.cycle, now if self.clock is None else self.clock())
            return
        self.service_inbox(now)
        self._supervise(now)
        self._rest_of_cycle(now)

    def _rest_of_cycle(self, now: float) -> None:
        """After the deadman: the control acts, outputs are written, changes recorded and
        published; then whether the next cycles may be quiet ones."""
        self.control.update(now)
        self._write()
        written = now if self.clock is None else self.clock()
        # The events and log lines of commands answered since the last cycle, outputs written.
        self.recorder.release()
        self._observe(now)
        self.publisher.publish(now, self.cycle, written)
        commands, tasks = self.commands_handled, self.tasks_run
        if self.quiet_cycles and commands == self._commands_seen and tasks == self._tasks_seen:
            self._rest = self._at_rest()
        # else: commands or tasks came since the last full cycle, and more may follow (a
        # stream makes every cycle a full one): the next cycle without any looks again.
        self._commands_seen, self._tasks_seen = commands, tasks

    def _write(self) -> None:
        """The cycle's outputs to the HAL; the charge pump, if the ride has one, changes level
        every cycle while nothing is faulted (an external relay keeps the drives powered only
        while it does: a stopped or faulted controller cannot keep them, docs/revpi.md). A
        latched watchdog and the E-stop's safe state write it low."""
        outputs = self.image.outputs
        if self._pump:
            outputs.pump = not outputs.pump and self.control.state not in FAULT_STATES
        self.hal.scan_outputs(outputs)

    # ----------------------------------------------------------------------- quiet cycles
    # An idle machine's cycle changes nothing: the same inputs, no controller, nothing queued.
    # After a full cycle that leaves the machine at such a rest, `_at_rest` notes what it
    # depended on (its `Snapshot` of the machine among them); a later cycle whose inputs,
    # commands, queued tasks, timers, parameters and machine all match it is quiet: it still
    # scans the inputs, runs the deadman and writes the outputs, and skips `update`, the event
    # history's compare and the publication work, whose results it knows (nothing). Anything
    # else runs the full cycle, which is the one definition of what a cycle does.

    def _at_rest(self) -> _Rest | None:
        """After a full cycle: what the next cycles must find to be quiet, or None when a
        repeat of this cycle could still do something (it would publish, record, move)."""
        shown = self.publisher.shown  # the machine as this cycle's publication found it
        if (
            shown is None
            or not self.control.at_rest()
            or self.publisher.unpublished
            or any(self.image.outputs.ro.values())  # `update` would switch them off
            or (self.guard is not None and self.guard.latched)
            or shown.estop_active
            or not self.axes.at_rest()
            or not self.recorder.settled(shown)
        ):
            return None
        inputs, watched = self.image.inputs, self.beats is not None and shown.rider is not None
        di, ai, commands, tasks = (
            dict(inputs.di),
            dict(inputs.ai),
            self.commands_handled,
            self.tasks_run,
        )
        changes = self.control.changes
        return _Rest(shown, changes, self.live.current, di, ai, commands, tasks, watched)

    def _verify_quiet(self, rest: _Rest) -> None:
        """What a quiet cycle took for granted, checked: nothing pending, the same machine."""
        control = self.control
        now = control.snapshot()
        if not control.at_rest() or now != rest.snapshot:
            raise AssertionError(f"cycle {self.cycle} was quiet, but {now} != {rest.snapshot}")

    def _take_watchdog_trip(self, now: float) -> bool:
        """The watchdog forced the outputs safe while the scan thread was stalled (and has
        published FAULT_HW already): make the machine state say so before the latch lets any
        output through again, and before any command is judged against the old state."""
        guard = self.guard
        if guard is None or not guard.latched:
            return False
        stalled = "" if guard.stalled_s is None else f" {guard.stalled_s * 1000:.0f} ms"
        self.control.external_fault(
            Fault(
                code=FaultCode.WATCHDOG,
                message=f"scan loop stalled{stalled}; the watchdog forced the outputs safe",
            ),
            now,
        )
        guard.unlatch()
        return True

    def _supervise(self, now: float) -> None:
        """Deadman: the controlling Rider's latest heartbeat (data from the bus) against `now`."""
        control = self.control
        rider = control.controller_rider
        if self.beats is None or rider is None:
            return
        before = control.state
        verdict = control.rider_heartbeat(self.beats.last_heartbeat(rider), now)
        if verdict is Verdict.LOST:
            loss = self.config.rider_loss
            log.warning(
                "event=rider_lost rider=%s cause=heartbeat timeout_s=%g policy=%s",
                rider,
                loss.timeout_s,
                loss.policy,
            )
            rider_event(self, "rider_lost", rider, control.state is not before, now)

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
        identity: Identity | None = None,
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
            return self.execute(command, request, clock(), sender=sender, identity=identity)
        finally:
            self.lock.release()

    def execute(
        self,
        command: Command,
        request: CommandRequest,
        now: float,
        *,
        sender: str | None = None,
        identity: Identity | None = None,
    ) -> Reply:
        """One command with at-most-once semantics by transaction id; `sender` the Rider it
        names as claimed, `identity` the same once confirmed (for the history)."""
        # Between cycles (from a Zenoh callback or the runner's queue) a Rider that saw the
        # watchdog's FAULT_HW and sent Home at once must find the machine in that fault, not
        # in the motion the stall interrupted; within a cycle `step` has taken it already.
        if self._take_watchdog_trip(now):
            self._observe(now)  # the fault and its notice, before the command's own
        self.commands_handled += 1
        live = self.live
        if live.offered is not live.current:
            # A parameter write answered before this command is in force for it: its reply
            # said so (issue 58: a Start sent on a `tilt.max_deg` write's reply was judged on
            # the old range). Between cycles, as at the start of one.
            live.take()
        stamp = now + self.wall_offset
        repeat = self.transactions.lookup(request.transaction_id, command._value_, stamp)
        if repeat is not None:
            self.recorder.command(
                self.control,
                command,
                request,
                repeat,
                now,
                sender=sender,
                identity=identity,
                repeat=True,
            )
            return repeat
        reply = self.control.handle(command, request, now)
        self.transactions.record(request.transaction_id, command._value_, reply)
        # Before the reply goes out: a Rider that asks for the notice at once finds the motion.
        self.publisher.collect()
        self.recorder.command(
            self.control,
            command,
            request,
            reply,
            now,
            sender=sender,
            identity=identity,
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

    def remember(
        self, replies: Iterable[tuple[str, str, bytes]], notices: Iterable[Completion]
    ) -> None:
        """Answers given before this start (the event history's): a repeat of a transaction
        gets its answer again, a late Rider the notice of its motion."""
        for tid, command, packed in replies:
            self.transactions.remember(tid, command, packed)
        for notice in notices:
            self.completions.record(notice)

    def _observe(self, now: float) -> None:
        """After the control acted: its notices into the log, its changes into the history."""
        self.publisher.collect()
        self.recorder.observe(self.control, now)

    def abort_motion(self, now: float, why: str) -> None:
        """On shutdown (the runner has stopped): a motion still under way ends `ABORTED`."""
        self.control.abort(now, why)
        self._observe(now)
        self.publisher.publish_completions()

    def go_safe(self) -> None:
        """Outputs off in the image and at the HAL, whatever state the loop is in."""
        self.image.all_outputs_off()
        self.hal.force_all_outputs_safe()

    def build_status(self, now: float) -> Status:
        """The status of the machine as it is now (a new sequence number)."""
        return self.publisher.status(now, self.cycle)

    def reject_pending(self, why: str) -> None:
        """On shutdown: every queued command still gets its one reply."""
        for task in self.inbox.close():
            task.reject(NotAvailable(why).to_error())
