"""What the gateway knows of each machine: the latest publications, kept as plain data.

The bus side writes it (one thread at a time: the gateway's event loop), the OPC UA side and the
Prometheus collector read it. No Zenoh, no OPC UA and no clock reads here: time comes in.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import CommandEvent, Event
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import Status

STORAGE_WARNING = ErrorCode.STORAGE_FAILED.value
"""How every status warning about the data directory starts (service/core/storage/persist.py)."""


@dataclass
class MachineView:
    """One machine as the gateway last heard it. `alive` follows its liveliness token."""

    machine_id: str
    alive: bool = True
    status: Status | None = None
    diag: CycleDiag | None = None
    io: dict[str, IoValue] = field(default_factory=dict)
    """By `<kind>/<name>`, e.g. `di/estop`."""
    axes: dict[str, AxisRecord] = field(default_factory=dict)
    commands: Counter[str] = field(default_factory=Counter)
    """Commands the machine answered since the gateway started, by reply or error code (from
    its `command` events)."""
    events_seen: int = 0
    left_at: float | None = None
    """When its token went (monotonic seconds); None while alive."""
    status_current: bool = False
    """Whether `status` was published or read since the machine (re)appeared: one kept from
    before its token went may be another run's, whose `seq` a restarted daemon begins again."""

    def apply(
        self, update: Status | CycleDiag | IoValue | AxisRecord, snapshot: bool = False
    ) -> None:
        """Keep a publication (a newer status never loses to an older one arriving late); a
        `snapshot` (a value read on request) never replaces a newer one."""
        if isinstance(update, Status):
            if self._takes(update, snapshot):
                self.status, self.status_current = update, True
        elif isinstance(update, CycleDiag):
            if not (snapshot and _newer(self.diag, update)):
                self.diag = update
        elif isinstance(update, IoValue):
            key = f"{update.kind}/{update.name}"
            if not (snapshot and _newer(self.io.get(key), update)):
                self.io[key] = update
        elif not (snapshot and _newer(self.axes.get(update.axis), update)):
            self.axes[update.axis] = update

    def _takes(self, update: Status, snapshot: bool) -> bool:
        """Whether `update` is newer than the status kept. A status read on request is taken
        by its `seq` alone: one read just before a publication may arrive after it (an
        E-stop pressed while the gateway was attaching read released, latched, released)."""
        if self.status is None or not self.status_current or update.seq >= self.status.seq:
            return True
        return not snapshot and update.seq < 2  # a publication that begins again: a restart

    def count(self, event: Event) -> None:
        """An event from the machine's history stream: commands are counted by code."""
        self.events_seen += 1
        if isinstance(event.details, CommandEvent) and not event.details.repeat:
            self.commands[event.details.code] += 1

    def presence(self, alive: bool, now: float) -> None:
        if alive != self.alive:
            self.status_current = False
        self.alive = alive
        self.left_at = None if alive else now

    @property
    def storage_warnings(self) -> int:
        """Status warnings about the data directory (a write that failed)."""
        if self.status is None:
            return 0
        return sum(w.startswith(STORAGE_WARNING) for w in self.status.warnings)


def _newer(
    kept: CycleDiag | IoValue | AxisRecord | None, update: CycleDiag | IoValue | AxisRecord
) -> bool:
    return kept is not None and kept.time > update.time
