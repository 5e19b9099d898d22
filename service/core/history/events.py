"""What the scan loop records: `EventRecorder` turns changes of the machine into event values.

Pure like the loop: no IO, no clock. It hands each event to an `EventSink` (the SQLite
writer in `service/adapters/eventlog.py`, or a list in tests) that must never block.
Transitions arrive as they happen; everything else is seen by comparing a small snapshot
after each command and cycle.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.completion import Completion
from ride_machine.schema.events import (
    CalibrationEvent,
    CompletionEvent,
    EstopEvent,
    EventKind,
    FaultEvent,
    KnownDetails,
    SessionEndedEvent,
    SessionStartedEvent,
    StateEvent,
    StorageEvent,
)
from ride_machine.schema.status import Fault, MachineState
from ride_machine.service.core.commands.identity import Identity
from ride_machine.service.core.motion.controllers import SessionRun
from ride_machine.service.core.motion.devices import Calibration
from ride_machine.service.core.statemachine import Snapshot, StateMachine, Transition

from .facts import CommandFacts
from .held import Emit, Held, Lazy, LogLine, hold_limit

S = MachineState


class EventSink(Protocol):
    """Takes events without waiting (a full queue counts the event as dropped)."""

    def emit(self, details: KnownDetails, time: float, cycle: int | None) -> None: ...

    def defer(self, held: Held) -> bool:
        """Take a command's held record to make on a thread of the sink's own, in its place
        among the events; False: the caller makes it now (`held.write(sink.emit)`)."""
        ...


class NullEventSink:
    """Records nothing (`[events] enabled = false`)."""

    def emit(self, details: KnownDetails, time: float, cycle: int | None) -> None:
        pass

    def defer(self, held: Held) -> bool:
        """Only the command's log line, at once: its events would be made to be dropped (half
        the commands of a stream made one such record before their reply)."""
        if held.then is not None:
            held.then()
        return True


@dataclass
class ListEventSink:
    """Keeps every event in a list (tests and the benchmark's baseline)."""

    events: list[tuple[KnownDetails, float, int | None]] = field(default_factory=list)

    def emit(self, details: KnownDetails, time: float, cycle: int | None) -> None:
        self.events.append((details, time, cycle))

    def defer(self, held: Held) -> bool:
        return False


@dataclass
class _Session:
    """The session under way, for its end event."""

    run: SessionRun
    transaction_id: str | None
    started: float


class EventRecorder:
    """Compares the machine before and after each command and cycle, and emits what changed."""

    def __init__(
        self,
        sink: EventSink,
        *,
        period_s: float,
        wall_offset: float = 0.0,
        persisted: bool = False,
    ):
        """`period_s`: the scan's period, which bounds the commands held for a cycle."""
        self.sink = sink
        self.wall_offset = wall_offset
        self.persisted = persisted
        """Calibration changes are written to data_dir (a store is configured)."""
        self.cycle = 0
        self._transitions: list[Transition] = []
        self._seen = False
        self._estop = False
        self._latched = False
        self._fault: Fault | None = None
        self._calibration: Calibration | None = None
        self._notices: list[Completion] = []
        self._session: _Session | None = None
        self._storage_version = 0
        self._storage_seen: set[str] = set()
        self._held: deque[Held] = deque()
        self.hold_limit = hold_limit(period_s)
        """Commands held for the next cycle at most."""

    # --------------------------------------------------------------------------- inputs
    def transition(self, t: Transition) -> None:
        """`StateMachine.on_transition`: kept until the next `observe`, so causes come first."""
        self._transitions.append(t)

    def command(  # noqa: PLR0913 - the command, its answer, who sent it (claimed, confirmed)
        self,
        control: StateMachine,
        command: Command,
        request: CommandRequest,
        reply: Reply,
        now: float,
        *,
        sender: str | None = None,
        identity: Identity | None = None,
        repeat: bool = False,
        logged: bool = False,
    ) -> None:
        """A command was answered: the command event, then what it changed. What changed is
        compared now (the state is the command's); the events are made and handed to the sink,
        and its log line written (`logged`), at the next `release`: off the path of its reply."""
        facts = CommandFacts.of(command, request, reply, sender, repeat, identity)
        rows: list[Lazy] = []
        wall = now + self.wall_offset
        self._compare(control, wall, rows.append, facts)
        held = self._held
        if len(held) >= self.hold_limit:
            self._hand_over(held.popleft())  # the oldest first: the order stays
        held.append(Held(rows, wall, self.cycle, LogLine(facts) if logged else None))

    @property
    def holding(self) -> bool:
        return bool(self._held)

    def release(self) -> None:
        """Hand over what `command` held, in order. The scan thread does it every cycle once
        the outputs are written; any later event, a history read and the shutdown do it first."""
        held = self._held
        while held:
            self._hand_over(held.popleft())

    def _hand_over(self, held: Held) -> None:
        """To the sink, which makes it on its own thread (the event log's writer), or made
        here when it will not take it."""
        if not self.sink.defer(held):
            held.write(self.sink.emit)

    def emit(self, details: KnownDetails, now: float) -> None:
        """One event from the scan loop itself (after what is held)."""
        self.release()
        self.sink.emit(details, now + self.wall_offset, self.cycle)

    def completion(self, notice: Completion) -> None:
        """A completion notice (service/core/commands/completions.py): recorded at the next
        `observe`, after
        the transitions that ended the motion."""
        self._notices.append(notice)

    # -------------------------------------------------------------------------- compare
    def observe(self, control: StateMachine, now: float) -> None:
        """Emit what changed since the last look (after what is held)."""
        self.release()
        wall = now + self.wall_offset
        self._compare(control, wall, self._emitter(wall), None)

    def _compare(self, control: StateMachine, wall: float, emit: Emit, cause: Lazy | None) -> None:
        """Emit, in this order: E-stop input changes, the command, the transitions, then
        their consequences (latch, faults, sessions, completions, calibration)."""
        if not self._seen:
            self._baseline(control)
        estop = control.devices.safety.is_estop_active()
        if estop != self._estop:
            self._estop = estop
            kind = "estop_pressed" if estop else "estop_released"
            emit(EstopEvent(kind=kind, state=control.state))
        if cause is not None:
            emit(cause)
        reason = ""
        for t in self._transitions:
            emit(StateEvent(old=t.old, new=t.new, reason=t.reason))
            reason = t.reason
        self._transitions.clear()
        if control.estop_latched != self._latched:
            self._latched = control.estop_latched
            kind = "estop_latched" if self._latched else "estop_reset"
            emit(EstopEvent(kind=kind, state=control.state, reason=reason))
        self._faults(control, emit)
        self._session_started(control, wall, emit)
        self._completions(wall, emit)
        self._calibrations(control, emit)
        self._storage(control, emit)

    def settled(self, now: Snapshot) -> bool:
        """Another `release` and `observe` of the machine as `now` shows it would emit
        nothing: nothing held, no transition or notice waiting, and what this recorder last
        saw matches it (`ScanLoop`'s quiet cycles)."""
        run = now.session
        return (
            self._seen
            and not self._held
            and not self._transitions
            and not self._notices
            and self._estop == now.estop_active
            and self._latched == now.estop_latched
            and self._fault == now.fault
            and self._calibration is now.calibration
            and now.storage == self._storage_version
            and (run is None or (self._session is not None and self._session.run is run))
        )

    def _emitter(self, wall: float) -> Emit:
        sink, cycle = self.sink, self.cycle

        def emit(details: Lazy) -> None:
            sink.emit(details() if callable(details) else details, wall, cycle)

        return emit

    def _baseline(self, control: StateMachine) -> None:
        self._seen = True
        self._estop = False  # an E-stop pressed at power-up is recorded as pressed
        self._latched = control.estop_latched
        self._fault = control.fault
        self._calibration = control.calibration

    def _faults(self, control: StateMachine, emit: Emit) -> None:
        fault = control.fault
        if fault == self._fault:
            return
        old, self._fault = self._fault, fault
        if old is not None:
            cleared = FaultEvent(
                kind="fault_cleared", code=old.code, message=old.message, axis=old.axis
            )
            emit(cleared)
        if fault is not None:
            emit(
                FaultEvent(
                    kind="fault_raised", code=fault.code, message=fault.message, axis=fault.axis
                )
            )

    def _session_started(self, control: StateMachine, wall: float, emit: Emit) -> None:
        run = control.context.drive.session_run
        if run is None or (self._session is not None and self._session.run is run):
            return
        action = control.action
        tid = action.transaction_id if action is not None else None
        self._session = _Session(run, tid, wall)
        progress = run.progress()
        emit(
            SessionStartedEvent(
                name=progress.name,
                steps=progress.step_count,
                revolutions_total=progress.revolutions_total,
                transaction_id=tid,
            )
        )

    def _completions(self, wall: float, emit: Emit) -> None:
        notices, self._notices = self._notices, []
        for notice in notices:
            session = self._session
            if session is not None and notice.transaction_id == session.transaction_id:
                p = session.run.progress()
                emit(
                    SessionEndedEvent(
                        name=p.name,
                        steps=p.step_count,
                        steps_done=min(p.step_index, p.step_count),
                        revolutions_done=p.revolutions_done,
                        revolutions_total=p.revolutions_total,
                        duration_s=round(wall - session.started, 3),
                        outcome=str(notice.outcome),
                    )
                )
                session.transaction_id = None  # ended; the run object stays for the status
            emit(
                CompletionEvent(
                    command=notice.command,
                    transaction_id=notice.transaction_id,
                    outcome=str(notice.outcome),
                    code=notice.code,
                    state=notice.state,
                    reason=notice.reason,
                )
            )

    def _storage(self, control: StateMachine, emit: Emit) -> None:
        """A calibration or parameter write to data_dir that failed (each problem once)."""
        storage = control.storage
        if storage is None or storage.version == self._storage_version:
            return
        self._storage_version = storage.version
        now = set(storage.warnings())
        for problem in sorted(now - self._storage_seen):
            emit(StorageEvent(what="data_dir", error=problem))
        self._storage_seen = now

    def _calibrations(self, control: StateMachine, emit: Emit) -> None:
        """A calibration change, once its write has ended: `persisted` says how it went."""
        cal = control.calibration
        old = self._calibration
        if cal is old:
            return
        ticket = control.keeper.save_ticket
        if ticket is not None and not ticket.done:
            return  # not settled: the loop looks again each cycle until the disk answers
        persisted = self.persisted if ticket is None else ticket.problem is None
        self._calibration = cal
        for axis in ("tilt", "rotate"):
            before, after = getattr(old, axis, None), getattr(cal, axis)
            if before != after:
                emit(
                    CalibrationEvent(
                        axis=axis,
                        old=dataclasses.asdict(before) if before is not None else None,
                        new=dataclasses.asdict(after) if after is not None else None,
                        persisted=persisted,
                    )
                )


__all__ = ["EventKind", "EventRecorder", "EventSink", "ListEventSink", "NullEventSink"]
