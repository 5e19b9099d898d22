"""`LiveView`: what the operator page shows, kept up to date from machine updates.

Pure logic: no Zenoh, no asyncio, no clock reads; time comes in as arguments. Every change
becomes a `Push` for the browsers; a browser that (re)connects starts from `snapshot()`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from ride_machine.rider.text import shown
from ride_machine.schema.axes import AxisRecord, PnStatus
from ride_machine.schema.calibration import CalibrationRecord
from ride_machine.schema.completion import Completion
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.io import IoKind, IoValue
from ride_machine.schema.status import Status

DEFAULT_HEARTBEAT_S = 1.0
"""The machine's status heartbeat (`bus.heartbeat_s`) until it has told its own."""
NOTICES_KEPT = 20
"""The latest completion notices, in every snapshot: a page cut off for falling behind (a busy
browser) reconnects with the notice its command waits for, not a reply that never ends."""


def lost_after(heartbeat_s: float) -> float:
    """No status for this long and the machine counts as lost: its heartbeat, late by half of
    it (at least 0.5 s, for a loaded host or link). 1.5 s at the default 1 s heartbeat."""
    return heartbeat_s + max(0.5, 0.5 * heartbeat_s)


LOST_AFTER_S = lost_after(DEFAULT_HEARTBEAT_S)

SAMPLE_PERIOD_S = 0.1
HISTORY_S = 60.0


@dataclass(frozen=True, slots=True)
class Presence:
    """The machine's liveliness token appeared (`alive`) or disappeared."""

    alive: bool


@dataclass(frozen=True, slots=True)
class Note:
    """What the bridge is doing while there is no machine to show (searching, no session...)."""

    text: str


@dataclass(frozen=True, slots=True)
class MachineFound:
    """The bridge settled on this machine id."""

    machine_id: str


Update = (
    Status
    | IoValue
    | AxisRecord
    | CycleDiag
    | Completion
    | CalibrationRecord
    | Presence
    | Note
    | MachineFound
)


@dataclass(frozen=True, slots=True)
class Push:
    """One message pushed to every browser (an event of the page's stream): a type and a
    JSON-ready body. Not the machine's history `Event` (schema.events)."""

    kind: str
    data: Any


@dataclass
class Link:
    """Whether the page's data is live, and if not, why."""

    up: bool = False
    reason: str = "connecting to the machine…"

    def as_json(self, machine_id: str | None) -> dict[str, Any]:
        return {"up": self.up, "reason": self.reason, "machine": machine_id}


@dataclass
class LiveView:
    """Latest status, IO, axes and diagnostics, the link state and a minute of history."""

    heartbeat_s: float = DEFAULT_HEARTBEAT_S
    sample_period_s: float = SAMPLE_PERIOD_S
    history_s: float = HISTORY_S
    machine_id: str | None = None
    status: Status | None = None
    io: dict[str, IoValue] = field(default_factory=dict)
    axes: dict[str, AxisRecord] = field(default_factory=dict)
    diag: CycleDiag | None = None
    calibration: CalibrationRecord | None = None
    link: Link = field(default_factory=Link)

    def __post_init__(self) -> None:
        self.history: deque[dict[str, Any]] = deque(
            maxlen=int(self.history_s / self.sample_period_s) + 1
        )
        self._status_at: float | None = None
        self._alive: bool | None = None
        self._note: str | None = None
        self._pending_ai: dict[str, IoValue] = {}
        self._next_sample = 0.0
        self.notices: deque[dict[str, Any]] = deque(maxlen=NOTICES_KEPT)

    @property
    def lost_after_s(self) -> float:
        return lost_after(self.heartbeat_s)

    # ------------------------------------------------------------------------------ input
    def apply(self, update: Update, now: float) -> list[Push]:
        """Take one update (at monotonic `now`); return the events to send at once."""
        events: list[Push] = []
        if isinstance(update, Status):
            self.status = update
            self._status_at = now
            self.heartbeat_s = update.heartbeat_s or DEFAULT_HEARTBEAT_S  # None: an older machine
            self._alive = True  # a fresh status proves the machine is there
            events.append(Push("status", shown(update).model_dump(mode="json")))
        elif isinstance(update, IoValue):
            self.io[update.name] = update
            if update.kind is IoKind.AI:
                self._pending_ai[update.name] = update  # analog changes batch to the next tick
            else:
                events.append(Push("io", [update.model_dump(mode="json")]))
        elif isinstance(update, AxisRecord):
            self.axes[update.axis] = update
        elif isinstance(update, CycleDiag):
            self.diag = update
            events.append(Push("diag", update.model_dump(mode="json")))
        elif isinstance(update, CalibrationRecord):
            self.calibration = update
            events.append(Push("calibration", update.model_dump(mode="json")))
        elif isinstance(update, Completion):
            # The page that sent the command waits for its own transaction's notice.
            notice = update.model_dump(mode="json")
            self.notices.append(notice)
            events.append(Push("done", notice))
        elif isinstance(update, Presence):
            self._alive = update.alive
        elif isinstance(update, Note):
            self._note = update.text
        elif isinstance(update, MachineFound):
            self.machine_id = update.machine_id
            self._note = None
        events += self._relink(now)
        return events

    def tick(self, now: float, wall: float) -> list[Push]:
        """Called every sample period: link timeout, batched analog IO, one plot sample."""
        events = self._relink(now)
        if self._pending_ai:
            events.append(
                Push("io", [p.model_dump(mode="json") for p in self._pending_ai.values()])
            )
            self._pending_ai.clear()
        if self.link.up and now >= self._next_sample:
            self._next_sample = now + self.sample_period_s * 0.5
            sample = self.sample(wall)
            self.history.append(sample)
            events.append(Push("sample", sample))
        return events

    # ----------------------------------------------------------------------------- output
    def sample(self, wall: float) -> dict[str, Any]:
        """The gauges' values now: angles (None = unknown), axis status bits and the state."""
        st = self.status
        return {
            "t": round(wall, 3),
            "tilt": self._angle("tilt", st.tilt_deg if st else None),
            "rotate": self._angle("rotate", st.rotate_deg if st else None),
            "tilt_bits": self.axes["tilt"].pn_status if "tilt" in self.axes else 0,
            "rotate_bits": self.axes["rotate"].pn_status if "rotate" in self.axes else 0,
            "state": st.state.value if st else None,
        }

    def snapshot(self, wall: float) -> dict[str, Any]:
        """Everything a browser needs to draw the page from scratch."""
        return {
            "now": wall,
            "link": self.link.as_json(self.machine_id),
            "status": shown(self.status).model_dump(mode="json") if self.status else None,
            "io": [p.model_dump(mode="json") for p in self.io.values()],
            "diag": self.diag.model_dump(mode="json") if self.diag else None,
            "calibration": self.calibration.model_dump(mode="json") if self.calibration else None,
            "sample": self.sample(wall) if self.status else None,
            "history": list(self.history),
            "done": list(self.notices),
        }

    # ---------------------------------------------------------------------------- helpers
    def _angle(self, axis: str, from_status: float | None) -> float | None:
        """The newest position: the axis stream while moving, else the status heartbeat."""
        record = self.axes.get(axis)
        if from_status is None or record is None or self.status is None:
            return from_status
        if record.time >= self.status.time and record.pn_status & PnStatus.DRIVE_ENABLED:
            return round(record.position_fb, 2)
        return from_status

    def _relink(self, now: float) -> list[Push]:
        up, reason = self._judge(now)
        if up == self.link.up and reason == self.link.reason:
            return []
        self.link = Link(up, reason)
        return [Push("link", self.link.as_json(self.machine_id))]

    def _judge(self, now: float) -> tuple[bool, str]:
        name = f"machine {self.machine_id}" if self.machine_id else "the machine"
        if self._alive is False:
            return False, f"{name} is gone (its liveliness token disappeared); reconnecting…"
        if self._status_at is None:
            return False, self._note or f"waiting for {name}…"
        if now - self._status_at > self.lost_after_s:
            return False, f"no status from {name} for over {self.lost_after_s:g} s; reconnecting…"
        return True, ""
