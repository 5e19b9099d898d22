"""A machine's alarms as OPC UA conditions (Part 9): their states, what changes them, and the
Acknowledge rules (pure: no OPC UA server, no clock reads; time comes in).

Each machine has, by name:
- `Estop`: active while its E-stop is pressed or latched;
- `Faulted`: active while the machine is in a fault state (FAULT_HW or FAULT_ESTOP);
- `Fault.<CODE>`: one per fault code, active while that fault is the machine's fault;
- `Lost`: active while its liveliness token is gone (stopped, crashed, frozen, cut off).

A condition that becomes active is unacknowledged; it is retained (shown in alarm lists and
sent again on ConditionRefresh) while it is active or not yet acknowledged. The states are
derived from each status the machine publishes, so a gateway started (or a SCADA connected)
after an E-stop still has the alarm.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import Enum

from ride_machine.schema.status import FAULT_STATES, FaultCode, Status

ESTOP = "Estop"
FAULTED = "Faulted"
LOST = "Lost"
FAULT_PREFIX = "Fault."


class ConditionClass(Enum):
    """Part 9's condition classes the gateway uses."""

    SAFETY = "Safety"
    PROCESS = "Process"
    SYSTEM = "System"


class AckRefused(Exception):
    """An Acknowledge that cannot be taken; `reason` names the OPC UA status."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass
class Condition:
    """One condition's state as of its last event."""

    machine_id: str
    name: str
    severity: int
    cls: ConditionClass
    input_path: str
    """The machine variable the condition follows (e.g. `EstopActive`)."""
    active: bool = False
    acked: bool = True
    message: str = ""
    active_since: float = 0.0
    """When it last became active or inactive (the machine's time)."""
    time: float = 0.0
    """Its last event's time."""
    event_id: bytes = b""
    comment: str = ""
    user: str = ""
    """Who acknowledged it last (the OPC UA user); empty: nobody yet."""

    @property
    def retain(self) -> bool:
        return self.active or not self.acked

    @property
    def condition_path(self) -> str:
        """Its ConditionId's string: `<machine>/Alarms/<name>`."""
        return f"{self.machine_id}/Alarms/{self.name}"

    def _event(self, when: float) -> Condition:
        self.time = when
        self.event_id = uuid.uuid4().bytes
        return self

    def set_active(self, active: bool, message: str, when: float) -> Condition | None:
        """The condition after an observation; None when nothing a client sees changed."""
        if active == self.active and (not active or message == self.message):
            return None
        if active != self.active:
            self.active_since = when
            if active:
                self.acked, self.comment, self.user = False, "", ""
        self.active, self.message = active, message
        return self._event(when)

    def acknowledge(self, event_id: bytes, comment: str, user: str, when: float) -> Condition:
        """Acknowledge the event `event_id` (its latest: an older one is a state already left)."""
        if event_id != self.event_id:
            raise AckRefused("BadEventIdUnknown")
        if self.acked:
            raise AckRefused("BadConditionBranchAlreadyAcked")
        self.acked, self.comment, self.user = True, comment, user
        return self._event(when)


@dataclass
class MachineConditions:
    """A machine's conditions by name (fault conditions are made at their first fault)."""

    machine_id: str
    by_name: dict[str, Condition] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._make(ESTOP, 900, ConditionClass.SAFETY, "EstopLatched")
        self._make(FAULTED, 700, ConditionClass.PROCESS, "State")
        self._make(LOST, 800, ConditionClass.SYSTEM, "Alive")

    def _make(self, name: str, severity: int, cls: ConditionClass, path: str) -> Condition:
        made = Condition(self.machine_id, name, severity, cls, path)
        self.by_name[name] = made
        return made

    def __iter__(self) -> Iterator[Condition]:
        return iter(self.by_name.values())

    def observe(self, status: Status) -> list[Condition]:
        """The conditions a status changed."""
        when = status.time
        estop = status.estop.active or status.estop.latched
        words = "pressed" if status.estop.active else "released, still latched"
        changed = [self.by_name[ESTOP].set_active(estop, f"E-stop {words}", when)]
        fault = status.fault
        why = f"{status.state}: {fault.code} {fault.message}" if fault else str(status.state)
        changed.append(self.by_name[FAULTED].set_active(status.state in FAULT_STATES, why, when))
        now: str | None = None
        if fault is not None and fault.code is not FaultCode.ESTOP:  # E-stop: its own condition
            now = FAULT_PREFIX + fault.code
            if now not in self.by_name:
                self._make(now, 700, ConditionClass.PROCESS, "FaultCode")
        for cond in self:
            if cond.name.startswith(FAULT_PREFIX):
                text = f"fault {cond.name.removeprefix(FAULT_PREFIX)}"
                if cond.name == now and fault is not None:
                    text += f": {fault.message}"
                changed.append(cond.set_active(cond.name == now, text, when))
        return [c for c in changed if c is not None]

    def presence(self, alive: bool, when: float) -> list[Condition]:
        """`Lost` follows the token."""
        text = "machine lost: its liveliness token is gone" if not alive else "machine back"
        changed = self.by_name[LOST].set_active(not alive, text, when)
        return [changed] if changed is not None else []

    def retained(self) -> list[Condition]:
        return [c for c in self if c.retain]
