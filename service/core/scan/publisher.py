"""What a full scan cycle publishes, and when: axes and IO as they change, the calibration when
it changes, the status when the machine's `Snapshot` differs from the one it last showed (or its
heartbeat is due), then the completion notices that status ends with. All through the loop's
one sink; the latest records kept as one immutable `Published` value for other threads.
"""

from __future__ import annotations

import logging

from ride_machine.schema.completion import Completion
from ride_machine.schema.status import Status
from ride_machine.service.core.commands.completions import CompletionLog
from ride_machine.service.core.history.events import EventRecorder
from ride_machine.service.core.motion.axes import AxisTracker
from ride_machine.service.core.motion.io import IoChanges, IoPoints
from ride_machine.service.core.statemachine import Snapshot, StateMachine
from ride_machine.service.core.statemachine.snapshot import status_of

from .sink import LoopSink, Published, calibration_record

log = logging.getLogger("machine")


class Publisher:
    """The loop's publications; on the scan thread only."""

    def __init__(
        self,
        state_machine: StateMachine,
        axes: AxisTracker,
        points: IoPoints,
        sink: LoopSink,
        recorder: EventRecorder,
        *,
        started_at: float,
    ) -> None:
        self.state_machine = state_machine
        self.axes = axes
        self.live = state_machine.live
        self.sink = sink
        self.recorder = recorder
        self.started_at = started_at
        self.io_changes = IoChanges(points)
        self.published = Published()
        """The latest records, replaced whole (never changed) when any of them changes."""
        self.completions = CompletionLog(self.live.current.bus.transaction_window)
        """Recent completion notices by transaction id (the bus answers `done/<id>` from it)."""
        self.unpublished: list[Completion] = []
        self.shown: Snapshot | None = None
        """The machine as the last status showed it."""
        self.status_due = 0.0
        """When the status is published again even if nothing changed (its heartbeat)."""
        self._seq = 0
        self._calibration_seen: object = None
        self._active_tid: str | None = None

    @property
    def wall_offset(self) -> float:
        """Wall time is `now + wall_offset` (the state machine's: it follows the host's clock)."""
        return self.state_machine.wall_offset

    def collect(self) -> None:
        """Take the machine's new notices into the log and the history; they are published
        after the status."""
        machine = self.state_machine
        notices = machine.context.take()
        for notice in notices:
            self.completions.hold(notice)  # answered once published, after its status
            self.recorder.completion(notice)
        self.unpublished += notices
        motion = machine.action
        tid = motion.transaction_id if motion is not None else None
        if tid != self._active_tid:
            self._active_tid = tid
            self.completions.set_active(motion.ref() if motion is not None else None)

    def publish(self, now: float, cycle: int, written: float) -> None:
        """A full cycle's publications; `written`: when its outputs were written."""
        wall = now + self.wall_offset
        machine, config = self.state_machine, self.live.current
        fault = machine.fault
        motion = machine.motion()
        self.axes.update(
            now,
            machine.state,
            fault.axis if fault else None,
            machine.calibration.rotate,
            motion,
            written,
        )
        old = self.published
        status, calibration, io, axes = old.status, old.calibration, old.io, old.axes
        records = [self.axes.record(name, cycle, wall) for name in self.axes.due(cycle)]
        if records:
            axes = {**axes, **{r.axis: r for r in records}}
        changed = self.io_changes.since_last(config.bus.ai_deadband_counts, wall)
        if changed:
            io = {**io, **{p.name: p for p in changed}}
        self.collect()
        if machine.calibration is not self._calibration_seen:
            self._calibration_seen = machine.calibration
            calibration = calibration_record(machine.calibration, config.machine.id, wall)
        shown = machine.snapshot()
        if shown != self.shown or now >= self.status_due:
            self.shown = shown
            self.status_due = now + config.bus.heartbeat_s
            status = self.status(now, cycle, shown)
        if status is not old.status or calibration is not old.calibration or records or changed:
            # Set before the publications: a Rider that hears one and asks finds it.
            self.published = Published(status, calibration, io, axes)
        self._remember_unpublished()  # a status query now finds the status they ended with
        sink = self.sink
        if records:
            sink.publish_axes(records)
        if changed:
            sink.publish_io(changed)
        if calibration is not None and calibration is not old.calibration:
            sink.publish_calibration(calibration)
        if status is not None and status is not old.status:
            sink.publish_status(status)
        if self.unpublished:
            self._send_completions()  # after the status: the seed's WARNING, then DONE

    def _remember_unpublished(self) -> None:
        """The notices not yet published, answerable by `done/<tid>`."""
        for notice in self.unpublished:
            self.completions.record(notice)

    def publish_completions(self) -> None:
        """Publish the notices due without a cycle's publication (a stop's abort)."""
        self._remember_unpublished()
        self._send_completions()

    def _send_completions(self) -> None:
        notices, self.unpublished = self.unpublished, []
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
            self.sink.publish_completion(notice)

    def status(self, now: float, cycle: int, shown: Snapshot | None = None) -> Status:
        """The status of the machine as `shown` (default: as it is now)."""
        machine, config = self.state_machine, self.live.current
        self._seq += 1
        storage = machine.storage
        tilt = machine.devices.tilt.read_position_degrees()
        rotate = self.axes.rotate.angle
        return status_of(
            machine.snapshot() if shown is None else shown,
            machine_id=config.machine.id,
            storage_warnings=storage.warnings() if storage is not None else [],
            tilt_deg=None if tilt is None else round(tilt, 2),
            rotate_deg=None if rotate is None else round(rotate, 1),
            seq=self._seq,
            cycle=cycle,
            time=now + self.wall_offset,
            uptime_s=round(now - self.started_at, 3),
            heartbeat_s=config.bus.heartbeat_s,
        )
