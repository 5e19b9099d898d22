"""The scan loop: read inputs → E-stop → commands → update → write outputs → publish.

`ScanLoop.step(now)` is a pure function of (inputs, queued commands, now); the real-time runner in
`service/core/scan/runner.py` calls it on absolute deadlines. Machine state has one writer at a
time, `ScanLoop.lock`: the scan thread holds it for each cycle; other threads see the loop only
through its port (`service/core/scan/port.py`): a command between cycles under the lock, any other
work put in the `Inbox`, what the loop published as immutable values (the records, whether it is
moving), read without the lock. It publishes through one sink.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from ride_machine.hal.base import Hal, Inputs
from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.completion import Completion
from ride_machine.schema.events import ClockEvent, RiderEvent
from ride_machine.schema.status import FAULT_STATES, Fault, FaultCode, Status
from ride_machine.service.config.model import LiveConfig, MachineConfig
from ride_machine.service.core.commands.identity import Identity
from ride_machine.service.core.commands.transactions import TransactionLog
from ride_machine.service.core.history.events import EventRecorder
from ride_machine.service.core.motion.axes import AxisTracker
from ride_machine.service.core.motion.devices import Devices
from ride_machine.service.core.motion.io import IoPoints, ProcessImage
from ride_machine.service.core.statemachine import Snapshot, StateMachine
from ride_machine.service.core.statemachine.deadman import Heartbeats, Verdict
from ride_machine.service.core.statemachine.signals import judge_signals
from ride_machine.service.errors import NotAvailable

from .inbox import Inbox
from .publisher import Publisher
from .sink import LoopSink, NullSink, Published
from .watchdog import GuardedHal

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

    def __init__(  # noqa: PLR0913 - keyword-only wiring of the loop's parts
        self,
        hal: Hal,
        state_machine: StateMachine,
        recorder: EventRecorder,
        *,
        sink: LoopSink | None = None,
        inbox: Inbox[ScanLoop] | None = None,
        started_at: float = 0.0,
        guard: GuardedHal | None = None,
        beats: Heartbeats | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        """`recorder`: the event history's; `guard`: the watchdog's HAL wrapper, whose latch
        this loop turns into a fault; `beats`: the Riders' heartbeats (the bus records them);
        without them (an in-process rig) only the controlling Rider's token is watched."""
        self.hal = hal
        self.guard = guard
        self.state_machine = state_machine
        self.live: LiveConfig = state_machine.live
        config = self.live.current
        self.devices: Devices = state_machine.devices
        self.points: IoPoints = self.devices.points
        self.image: ProcessImage = self.points.image
        self.beats = beats
        self.inbox: Inbox[ScanLoop] = inbox or Inbox(config.bus.inbox_capacity)
        self.transactions = TransactionLog(config.bus.transaction_window)
        self.axes = AxisTracker(self.devices, self.live)
        self.recorder = recorder
        sink = NullSink() if sink is None else sink  # the loop's one outbound channel
        parts = (state_machine, self.axes, self.points, sink, self.recorder)
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
        self.clock = clock
        """The clock `now` is read from, when it is a real one: the output write is stamped on
        it, so the rotate's dead reckoning counts the time a cycle took from its input scan to
        its relays (docs/homing.md). None: outputs are written at `now` (a fake clock)."""
        self.moving = state_machine.is_moving()
        """Motion under way or resumable, as the latest cycle or command left it: a value any
        thread reads without the lock (`LoopPort.moving`)."""

    @property
    def config(self) -> MachineConfig:
        """The running config (online parameters change it at a cycle boundary)."""
        return self.live.current

    @property
    def wall_offset(self) -> float:
        """Wall time is `now + wall_offset`: the state machine's, which every part reads."""
        return self.state_machine.wall_offset

    def set_wall_offset(self, offset: float, now: float, *, record: bool = True) -> None:
        """The host's clock moved against the steady one: wall times from `now` on are
        `now + offset` (the runner follows the host's clock, `RealtimeRunner`). A step that
        was set (`record`) is logged and recorded; a drift followed bit by bit is not."""
        step = offset - self.state_machine.wall_offset
        self.state_machine.wall_offset = self.recorder.wall_offset = offset
        if record:
            log.warning("event=clock_set step_s=%.3f", step)
            self.recorder.emit(ClockEvent(step_s=round(step, 6)), now)

    @property
    def published(self) -> Published:
        """The latest records, one immutable value (`LoopPort.published`)."""
        return self.publisher.published

    # ------------------------------------------------------------------------------ cycle
    def step(self, now: float) -> None:
        """One scan cycle, in the design's order (6., the sleep to the next deadline, is the
        runner's)."""
        self.cycle = self.recorder.cycle = self.cycle + 1
        if self.live.offered is not self.live.current:
            self.live.take()  # online parameter writes take effect here, between cycles
        inputs = self.image.inputs = self.hal.scan_inputs()  # 1. the inputs
        if self._rest is not None and self._quiet(self._rest, inputs, now):  # see quiet cycles
            return
        self._take_watchdog_trip(now)
        if self.devices.safety.is_estop_active():  # 2. E-stop, in the cycle it is seen
            self._estop(now)
            return
        self.service_inbox(now)  # 3. queued commands, one reply each
        self._supervise(now)  # the controlling Rider's deadman
        judge_signals(self.state_machine, now)  # a broken sensor wire, at rest too
        self.state_machine.update(now)  # 4. the state machine steps its controllers
        self._write_and_publish(now)  # 5. the outputs, then what changed, published

    def _estop(self, now: float) -> None:
        """Same cycle the input is seen: state, controllers and outputs, before anything else;
        then commands are refused with ESTOP_ACTIVE, checks answered, and it is published."""
        self.state_machine.on_estop(now)
        self.go_safe()
        self._observe(now)
        self.service_inbox(now)
        self.publisher.publish(now, self.cycle, now if self.clock is None else self.clock())
        self.moving = self.state_machine.is_moving()

    def _write_and_publish(self, now: float) -> None:
        """After the state machine acted: outputs written, changes recorded and published;
        then whether the next cycles may be quiet ones."""
        self._write()
        written = now if self.clock is None else self.clock()
        # The events and log lines of commands answered since the last cycle, outputs written.
        self.recorder.release()
        self._observe(now)
        self.publisher.publish(now, self.cycle, written)
        self.moving = self.state_machine.is_moving()
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
            outputs.pump = not outputs.pump and self.state_machine.state not in FAULT_STATES
        self.hal.scan_outputs(outputs)

    # ----------------------------------------------------------------------- quiet cycles
    # An idle machine's cycle changes nothing: the same inputs, no controller, nothing queued.
    # After a full cycle that leaves the machine at such a rest, `_at_rest` notes what it
    # depended on (its `Snapshot` of the machine among them); a later cycle whose inputs,
    # commands, queued tasks, timers, parameters and machine all match it is quiet: it still
    # scans the inputs, runs the deadman and writes the outputs, and skips `update`, the event
    # history's compare and the publication work, whose results it knows (nothing). Anything
    # else runs the full cycle, which is the one definition of what a cycle does.

    def _quiet(self, rest: _Rest, inputs: Inputs, now: float) -> bool:
        """After a full cycle that left the machine at `rest`: this cycle done here (True)
        when it reads nothing that one did not: the same inputs, no command or task since,
        nothing queued, no output on, no latch, the same parameters, the status heartbeat not
        due. Then the deadman runs, and if it did not act the outputs are written; if it
        acted, the rest of a full cycle runs."""
        self._rest = None  # until this cycle is found quiet
        guard = self.guard
        # Written out here, where every idle cycle runs it: after a 10 ms sleep each Python
        # call costs microseconds of cold caches (BENCHMARKS.md section 5).
        if (
            inputs.di != rest.di
            or inputs.ai != rest.ai
            or now >= self.publisher.status_due  # the status heartbeat is a full cycle
            or self.commands_handled != rest.commands
            or self.tasks_run != rest.tasks
            or self.inbox.wake.flag  # set whenever something is queued
            or any(self.image.outputs.ro.values())
            or (guard is not None and guard.latched)
            or self.live.current is not rest.config  # new parameters: a full cycle takes them in
        ):
            return False
        # Of the state machine only the deadman runs here; whatever acts on it counts in
        # `changes`, and of what it shows other threads change only the data dir's health.
        # So the machine is as `rest.snapshot` unless these say otherwise (`verify_quiet`
        # checks that against a fresh snapshot in the tests).
        if rest.watched:
            self._supervise(now)
        machine = self.state_machine
        storage = machine.storage
        if machine.changes != rest.changes or (
            storage is not None and storage.version != rest.snapshot.storage
        ):
            machine.update(now)  # the deadman acted: the rest of a full cycle
            self._write_and_publish(now)
            return True
        # Quiet: what a full cycle does at rest, without the work that finds nothing.
        self._rest = rest
        self._write()
        self.axes.tick(now)
        self.quiet += 1
        if self.verify_quiet:
            self._verify_quiet(rest)
        return True

    def _at_rest(self) -> _Rest | None:
        """After a full cycle: what the next cycles must find to be quiet, or None when a
        repeat of this cycle could still do something (it would publish, record, move)."""
        shown = self.publisher.shown  # the machine as this cycle's publication found it
        if (
            shown is None
            or not self.state_machine.at_rest()
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
        changes = self.state_machine.changes
        return _Rest(shown, changes, self.live.current, di, ai, commands, tasks, watched)

    def _verify_quiet(self, rest: _Rest) -> None:
        """What a quiet cycle took for granted, checked: nothing pending, the same machine."""
        machine = self.state_machine
        now = machine.snapshot()
        if not machine.at_rest() or now != rest.snapshot:
            raise AssertionError(f"cycle {self.cycle} was quiet, but {now} != {rest.snapshot}")

    def _take_watchdog_trip(self, now: float) -> bool:
        """The watchdog forced the outputs safe while the scan thread was stalled (and has
        published FAULT_HW already): make the machine state say so before the latch lets any
        output through again, and before any command is judged against the old state."""
        guard = self.guard
        if guard is None or not guard.latched:
            return False
        stalled = "" if guard.stalled_s is None else f" {guard.stalled_s * 1000:.0f} ms"
        self.state_machine.external_fault(
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
        machine = self.state_machine
        rider = machine.controller_rider
        if self.beats is None or rider is None:
            return
        self.beats.controller = rider  # its heartbeats are never dropped to make room
        before = machine.state
        verdict = machine.rider_heartbeat(self.beats.last_heartbeat(rider), now)
        if verdict is Verdict.LOST:
            loss = self.config.rider_loss
            log.warning(
                "event=rider_lost rider=%s cause=heartbeat timeout_s=%g policy=%s",
                rider,
                loss.timeout_s,
                loss.policy,
            )
            self.rider_event("rider_lost", rider, machine.state is not before, now)

    def rider_event(self, kind: str, rider: str, acted: bool, now: float) -> None:
        """A Rider came back or was lost (`acted`: the policy paused or stopped it), into the
        history through the recorder: after what it holds (the events of commands answered
        since the last cycle), before the state change this causes."""
        # Left at rest (the end of `rider start --wait`) or lost while its motion runs; after a
        # stop only `acted` tells.
        mid_motion = acted or self.state_machine.is_moving()
        policy = str(self.config.rider_loss.policy)
        event = RiderEvent(
            kind=kind, rider=rider, policy=policy, acted=acted, mid_motion=mid_motion
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
                self.state_machine,
                command,
                request,
                repeat,
                now,
                sender=sender,
                identity=identity,
                repeat=True,
            )
            return repeat
        reply = self.state_machine.handle(command, request, now)
        self.moving = self.state_machine.is_moving()  # before the reply: a write on its heels
        self.transactions.record(request.transaction_id, command._value_, reply)
        # Before the reply goes out: a Rider that asks for the notice at once finds the motion.
        self.publisher.collect()
        self.recorder.command(
            self.state_machine,
            command,
            request,
            reply,
            now,
            sender=sender,
            identity=identity,
            logged=True,
        )
        return reply

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
        """After the state machine acted: its notices into the log, its changes into the
        history."""
        self.publisher.collect()
        self.recorder.observe(self.state_machine, now)

    def abort_motion(self, now: float, why: str) -> None:
        """On shutdown (the runner has stopped): a motion still under way ends `ABORTED`."""
        self.state_machine.abort(now, why)
        self.moving = self.state_machine.is_moving()
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
