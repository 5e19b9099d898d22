"""The event history's wire models: one details model per kind of event (told apart by
`kind`), an event as stored and read, and a page of them as the `events` queryable replies."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from .base import OpenWireModel
from .status import MachineState

ParamScalar = bool | int | float | str


class CommandEvent(OpenWireModel):
    """A command reached the scan loop: who sent it, and whether it was accepted."""

    kind: Literal["command"] = "command"
    command: str | None
    transaction_id: str | None = None
    rider: str | None = None
    """The Rider the request named (`<login>/<zid>`, its `rider` field or its attachment), as
    its sender claimed it."""
    identity: str | None = None
    """The same Rider once it confirmed that it sent this request (`rider/<login>/<zid>/confirm`,
    schema/rider.py): under the ACL profiles only that login can answer there, so this is
    proof of the login. None: `rider` is a claim nobody confirmed (or a Pause, Stop or check,
    which are taken from anyone at once and not asked about)."""
    operator: str | None = None
    """The person the confirming Rider acted for, as it named them in its confirmation (the
    plant gateway's OPC UA user or certificate subject); None: the Rider named nobody."""
    accepted: bool
    code: str
    """The reply code when accepted (e.g. RESP_START_ACCEPTED), the error code when refused."""
    message: str = ""
    state: MachineState | None = None
    repeat: bool = False
    """A retry of a transaction already answered: the same reply again, nothing acted twice."""


class CompletionEvent(OpenWireModel):
    """A motion command ended: DONE, stopped, or a fault, with the transaction it ends."""

    kind: Literal["completion"] = "completion"
    command: str | None
    transaction_id: str | None = None
    outcome: str
    """As the completion notice says (schema/completion.py): DONE, STOPPED, FAULT_HW,
    FAULT_ESTOP, REFUSED, STORAGE_FAILED or ABORTED; see `code` and `reason`."""
    code: str | None = None
    state: MachineState
    reason: str = ""


class StateEvent(OpenWireModel):
    """A state transition with the reason the state machine gave."""

    kind: Literal["state"] = "state"
    old: MachineState
    new: MachineState
    reason: str = ""


class FaultEvent(OpenWireModel):
    """A fault raised, or the fault that was active cleared (by a new command or Stop)."""

    kind: Literal["fault_raised", "fault_cleared"]
    code: str
    message: str = ""
    axis: str | None = None


class EstopEvent(OpenWireModel):
    """The E-stop input pressed or released; the latch set, or reset by a command."""

    kind: Literal["estop_pressed", "estop_released", "estop_latched", "estop_reset"]
    state: MachineState | None = None
    reason: str = ""


class SessionStartedEvent(OpenWireModel):
    kind: Literal["session_started"] = "session_started"
    name: str
    steps: int
    revolutions_total: int
    transaction_id: str | None = None


class SessionEndedEvent(OpenWireModel):
    kind: Literal["session_ended"] = "session_ended"
    name: str
    steps: int
    steps_done: int
    revolutions_done: int
    revolutions_total: int
    duration_s: float
    outcome: str
    """As the Start's completion notice: DONE, STOPPED, FAULT_HW, FAULT_ESTOP, ABORTED."""


class CalibrationEvent(OpenWireModel):
    """An axis calibration changed (old → new values); `persisted` when written to data_dir."""

    kind: Literal["calibration"] = "calibration"
    axis: str
    old: dict[str, float | str | None] | None = None
    new: dict[str, float | str | None] | None = None
    """The axis's values, with `source` (measured / manual) and `at` (when)."""
    persisted: bool


class ParamEvent(OpenWireModel):
    """An online parameter written (or reset to its default) over the bus; a safety setting's
    write (service/core/storage/safety.py) is a `safety_changed` event, refused ones included."""

    kind: Literal["param_changed", "safety_changed"] = "param_changed"
    name: str
    old: ParamScalar
    new: ParamScalar
    persisted: bool
    reset: bool = False
    transaction_id: str | None = None
    by: str | None = None
    """Who asked: the Rider id (`<login>/<zid>`) the write came with, as its sender said it."""
    identity: str | None = None
    """`by` once that Rider confirmed it sent the write (as `CommandEvent.identity`); None:
    `by` is only claimed."""
    operator: str | None = None
    """As `CommandEvent.operator`."""
    accepted: bool = True
    """False: refused (`message` says why; `new` is what was asked), nothing changed."""
    message: str = ""


class RiderEvent(OpenWireModel):
    """The controlling Rider's liveliness token went away or came back."""

    kind: Literal["rider_lost", "rider_returned"]
    rider: str
    policy: str = ""
    acted: bool = False
    """On loss: the policy acted at once (False: no motion, or a grace period runs)."""
    mid_motion: bool | None = None
    """A motion was under way, paused or held by the E-stop when the Rider went (False: it
    left a machine at rest); None from a machine older than this field."""


class WatchdogEvent(OpenWireModel):
    kind: Literal["watchdog_trip"] = "watchdog_trip"
    stalled_s: float


class ClockEvent(OpenWireModel):
    """The host's wall clock was set while the daemon ran (NTP's first sync on a Revolution Pi,
    which has no battery clock; a hand-set date; a virtual machine resumed): wall times, and the
    timecodes commands are checked against, follow it from this event on."""

    kind: Literal["clock_set"] = "clock_set"
    step_s: float
    """How far the wall clock moved against the scan's steady clock (positive: forward)."""


class DaemonStartEvent(OpenWireModel):
    kind: Literal["daemon_start"] = "daemon_start"
    pid: int
    hal: str
    period_s: float
    previous_stop_clean: bool | None = None
    """False when the log's last run ended without a `daemon_stop` (killed or crashed)."""
    safety: dict[str, ParamScalar] | None = None
    """The safety settings this run started with (the config file's, or stricter persisted
    online values): the record of what the file set, beside `safety_changed` for the bus."""


class DaemonStopEvent(OpenWireModel):
    kind: Literal["daemon_stop"] = "daemon_stop"
    reason: str
    exit_code: int


class StorageEvent(OpenWireModel):
    """A write to data_dir failed (the event log itself, calibration, parameters)."""

    kind: Literal["storage_failed"] = "storage_failed"
    what: str
    error: str
    lost: int = 0
    """Events that could not be written because of it (for the event log)."""


class DroppedEvent(OpenWireModel):
    """Events the scan loop produced while the writer's queue was full (never written)."""

    kind: Literal["events_dropped"] = "events_dropped"
    count: int


KnownDetails = Annotated[
    CommandEvent
    | CompletionEvent
    | StateEvent
    | FaultEvent
    | EstopEvent
    | SessionStartedEvent
    | SessionEndedEvent
    | CalibrationEvent
    | ParamEvent
    | RiderEvent
    | WatchdogEvent
    | ClockEvent
    | DaemonStartEvent
    | DaemonStopEvent
    | StorageEvent
    | DroppedEvent,
    Field(discriminator="kind"),
]
Details = Annotated[KnownDetails | dict[str, Any], Field(union_mode="left_to_right")]


class Event(OpenWireModel):
    """One row of the event log: `seq` only grows (never reused, even after pruning)."""

    seq: int
    time: float
    """Wall-clock seconds (Unix time)."""
    cycle: int | None = None
    """The scan cycle it happened in; None for events from outside the scan loop."""
    machine_id: str
    kind: str
    details: Details

    @model_validator(mode="after")
    def _kind_matches(self) -> Event:
        tag = self.details.get("kind") if isinstance(self.details, dict) else self.details.kind
        if tag != self.kind:
            raise ValueError(f"details are of kind {tag!r}, the event of kind {self.kind!r}")
        return self


class EventPage(OpenWireModel):
    """One reply of the `events` queryable; ask again from `next_since` while `more`."""

    machine_id: str
    events: list[Event]
    more: bool
    next_since: int | None = None
    first_seq: int | None = None
    """The oldest seq still kept (older ones were pruned by retention)."""
    last_seq: int | None = None
