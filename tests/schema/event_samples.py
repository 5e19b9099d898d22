"""One sample of every event-history wire model, for the codec's round-trip test."""

from __future__ import annotations

from pydantic import BaseModel

from ride_machine.common.event_summary import EventSummary
from ride_machine.schema import events
from ride_machine.schema.diag import EventsDiag
from ride_machine.schema.status import MachineState

S = MachineState

DETAILS: list[BaseModel] = [
    events.CommandEvent(
        command="Start",
        transaction_id="t1",
        rider="abc",
        accepted=False,
        code="WRONG_STATE",
        message="Start is not accepted in RUNNING",
        state=S.RUNNING,
    ),
    events.CompletionEvent(
        command="Home", transaction_id="t2", outcome="DONE", state=S.IDLE, reason="Home complete"
    ),
    events.StateEvent(old=S.IDLE, new=S.RUNNING, reason="Start session 'default'"),
    events.FaultEvent(kind="fault_raised", code="TILT_TIMEOUT", message="late", axis="tilt"),
    events.EstopEvent(kind="estop_latched", state=S.FAULT_ESTOP, reason="E-stop pressed"),
    events.SessionStartedEvent(name="default", steps=2, revolutions_total=3, transaction_id="t3"),
    events.SessionEndedEvent(
        name="default",
        steps=2,
        steps_done=1,
        revolutions_done=1,
        revolutions_total=3,
        duration_s=4.5,
        outcome="FAULT_HW",
    ),
    events.CalibrationEvent(
        axis="tilt",
        old=None,
        new={"offset_counts": 1.0, "gain_counts_per_deg": 40.0},
        persisted=True,
    ),
    events.ParamEvent(
        name="tilt.tolerance_deg", old=1.0, new=1.5, persisted=True, transaction_id="t4"
    ),
    events.RiderEvent(kind="rider_lost", rider="abc", policy="pause", acted=True),
    events.RiderEvent(
        kind="rider_lost", rider="abd", policy="pause", acted=False, mid_motion=False
    ),
    events.WatchdogEvent(stalled_s=0.25),
    events.ClockEvent(step_s=11.6),
    events.DaemonStartEvent(pid=42, hal="sim", period_s=0.01, previous_stop_clean=False),
    events.DaemonStopEvent(reason="signal SIGTERM", exit_code=0),
    events.StorageEvent(what="events", error="disk I/O error", lost=3),
    events.DroppedEvent(count=7),
]
EVENT = events.Event(
    seq=9, time=1.5, cycle=100, machine_id="m1", kind="command", details=DETAILS[0]
)
EVENT_SAMPLES: list[BaseModel] = [
    *DETAILS,
    EVENT,
    events.EventPage(
        machine_id="m1", events=[EVENT], more=True, next_since=10, first_seq=1, last_seq=12
    ),
    EventSummary(
        machine_id="m1",
        since=0.0,
        until=None,
        events=1,
        sessions_started=1,
        sessions_done=1,
        sessions_stopped=0,
        sessions_faulted=0,
        ride_time_s=12.5,
        estops=1,
        faults_by_code={"TILT_TIMEOUT": 1},
        commands=3,
        commands_refused=1,
        daemon_starts=1,
        unclean_stops=0,
        dropped=0,
    ),
    EventsDiag(written=5, queued=1, dropped=2, lost=0, failures=0, file_bytes=4096),
]
