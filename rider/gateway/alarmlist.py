"""The machines' conditions (rider/gateway/conditions.py) on the wire: `AlarmConditionType`
events to every subscription watching the Server object or the machine's, `ConditionRefresh`
(`ConditionRefresh2`) for any session that may subscribe, and `Acknowledge` for the operator.

Condition instances are not nodes of the address space (OPC UA Part 9, 5.5.2 allows it): a
condition's ConditionId is `ns=<gateway ns>;s=<machine>/Alarms/<name>`, and Acknowledge is
called with it as the ObjectId, as Part 9 (5.7.3) requires servers to accept. So a forgotten
machine's `Lost` alarm stays in alarm lists, acknowledgeable, after its object is gone.

Events reach subscriptions through asyncua's monitored item service (`_monitored_events`,
`_trigger_event`: asyncua 2.x, pinned by requirements/ and tests/gateway/test_alarms.py);
asyncua's own refresh is not used (it keeps one event object per condition and mutates it).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterable
from datetime import UTC, datetime
from typing import Any

from asyncua import ua
from asyncua.common import event_objects
from asyncua.server.internal_server import InternalServer

from ride_machine.schema.status import Status

from .calls import Calls, Invocation, Role
from .conditions import AckRefused, Condition, ConditionClass, MachineConditions

log = logging.getLogger(__name__)

_I = ua.ObjectIds
_S = ua.StatusCodes
SERVER = ua.NodeId(_I.Server)
ACKNOWLEDGE = ua.NodeId(_I.AcknowledgeableConditionType_Acknowledge)
REFRESH = ua.NodeId(_I.ConditionType_ConditionRefresh)
REFRESH2 = ua.NodeId(_I.ConditionType_ConditionRefresh2)
_WIRE_TYPES = {
    ua.NodeId(_I.UtcTime): ua.VariantType.DateTime,
    ua.NodeId(_I.Duration): ua.VariantType.Double,
    ua.NodeId(_I.AudioDataType): ua.VariantType.ByteString,
}
"""asyncua's event classes give some fields a DataType node, not a variant type: the built-in
type each is encoded as."""
CLASSES = {
    ConditionClass.SAFETY: (_I.SafetyConditionClassType, "Safety"),
    ConditionClass.PROCESS: (_I.ProcessConditionClassType, "Process"),
    ConditionClass.SYSTEM: (_I.SystemConditionClassType, "System"),
}


def _time(t: float) -> datetime:
    return datetime.fromtimestamp(t, UTC)


def _state(name: str, on: bool, true: str, false: str) -> dict[str, Any]:
    """A TwoStateVariable's fields, as event fields (`ActiveState`, `ActiveState/Id`, …)."""
    return {
        name: ua.LocalizedText(true if on else false),
        f"{name}/Id": on,
        f"{name}/TrueState": ua.LocalizedText(true),
        f"{name}/FalseState": ua.LocalizedText(false),
    }


class AlarmList:
    """Every machine's conditions, and the methods that work on them."""

    def __init__(self, iserver: InternalServer, calls: Calls) -> None:
        self._iserver = iserver
        self.idx = 0
        self.machines: dict[str, MachineConditions] = {}
        calls.bind(ACKNOWLEDGE, Role.OPERATOR, self.acknowledge)
        calls.bind(REFRESH, Role.SESSION, self.refresh)
        calls.bind(REFRESH2, Role.SESSION, self.refresh)
        calls.virtual = self.knows

    def of(self, machine_id: str) -> MachineConditions:
        found = self.machines.get(machine_id)
        if found is None:
            found = self.machines[machine_id] = MachineConditions(machine_id)
        return found

    def knows(self, object_id: ua.NodeId) -> bool:
        """Whether `object_id` is a condition's ConditionId."""
        return self._find(object_id) is not None

    def retained(self) -> list[Condition]:
        return [c for machine in self.machines.values() for c in machine.retained()]

    # ----------------------------------------------------------------------- changes
    async def status(self, machine_id: str, status: Status) -> None:
        await self.emit(self.of(machine_id).observe(status))

    async def presence(self, machine_id: str, alive: bool, when: float) -> None:
        await self.emit(self.of(machine_id).presence(alive, when))

    async def emit(self, changed: Iterable[Condition]) -> None:
        """Each changed condition's event to every subscription that watches for it."""
        for cond in changed:
            log.info(
                "event=condition machine=%s condition=%s active=%s acked=%s retain=%s",
                cond.machine_id,
                cond.name,
                cond.active,
                cond.acked,
                cond.retain,
            )
            event = self.event_of(cond)
            for sub in list(self._iserver.subscription_service.subscriptions.values()):
                for notifier in (SERVER, ua.NodeId(cond.machine_id, self.idx)):
                    event.emitting_node = notifier
                    await sub.monitored_item_srv.trigger_event(event)

    def event_of(self, cond: Condition) -> Any:
        """The condition's state as an `AlarmConditionType` event."""
        source = ua.NodeId(cond.machine_id, self.idx)
        event = event_objects.AlarmCondition(sourcenode=source, severity=cond.severity)
        event.add_property("NodeId", self.condition_id(cond), ua.VariantType.NodeId)
        for name, dtype in event.data_types.items():
            if isinstance(dtype, ua.NodeId):
                event.data_types[name] = _WIRE_TYPES[dtype]
        class_id, class_name = CLASSES[cond.cls]
        fields: dict[str, Any] = {
            "EventId": cond.event_id,
            "SourceName": cond.machine_id,
            "Time": _time(cond.time),
            "ReceiveTime": datetime.now(UTC),
            "Message": ua.LocalizedText(cond.message),
            "ConditionClassId": ua.NodeId(class_id),
            "ConditionClassName": ua.LocalizedText(class_name),
            "ConditionName": cond.name,
            "BranchId": ua.NodeId(),
            "Retain": cond.retain,
            "Quality": ua.StatusCode(),
            "LastSeverity": cond.severity,
            "Comment": ua.LocalizedText(cond.comment),
            "ClientUserId": cond.user,
            "InputNode": ua.NodeId(f"{cond.machine_id}/{cond.input_path}", self.idx),
            "SuppressedOrShelved": False,
            "ActiveState/TransitionTime": _time(cond.active_since),
            **_state("EnabledState", True, "Enabled", "Disabled"),
            **_state("AckedState", cond.acked, "Acknowledged", "Unacknowledged"),
            **_state("ActiveState", cond.active, "Active", "Inactive"),
        }
        for name, value in fields.items():
            setattr(event, name, value)
        return event

    def condition_id(self, cond: Condition) -> ua.NodeId:
        return ua.NodeId(cond.condition_path, self.idx)

    def _find(self, object_id: ua.NodeId) -> Condition | None:
        ident = object_id.Identifier
        if object_id.NamespaceIndex != self.idx or not isinstance(ident, str):
            return None
        machine_id, _, rest = ident.partition("/Alarms/")
        machine = self.machines.get(machine_id)
        return machine.by_name.get(rest) if machine is not None else None

    # ----------------------------------------------------------------------- methods
    async def acknowledge(self, call: Invocation) -> ua.CallMethodResult:
        """`Acknowledge(EventId, Comment)` on a ConditionId (Part 9, 5.7.3), for the operator;
        the acknowledging user is the event's ClientUserId."""
        cond = self._find(call.object_id)
        if cond is None:
            return _status(_S.BadNodeIdUnknown)
        if len(call.arguments) != 2:
            short = len(call.arguments) < 2
            return _status(_S.BadArgumentsMissing if short else _S.BadTooManyArguments)
        event_id, comment = (a.Value for a in call.arguments)
        if not isinstance(event_id, bytes) or not isinstance(comment, ua.LocalizedText | None):
            return _status(_S.BadTypeMismatch)
        text = comment.Text if comment is not None and comment.Text else ""
        try:
            cond.acknowledge(event_id, text, call.caller.name or "", datetime.now(UTC).timestamp())
        except AckRefused as refused:
            return _status(getattr(_S, refused.reason))
        await self.emit([cond])
        return ua.CallMethodResult()

    async def refresh(self, call: Invocation) -> ua.CallMethodResult:
        """`ConditionRefresh(SubscriptionId)` and `ConditionRefresh2(SubscriptionId,
        MonitoredItemId)`: RefreshStart, every retained condition, RefreshEnd, to the calling
        session's own subscription (Part 9, 5.5.7)."""
        two = call.method_id == REFRESH2
        wanted = [a.Value for a in call.arguments]
        if len(wanted) != (2 if two else 1):
            short = len(wanted) < (2 if two else 1)
            return _status(_S.BadArgumentsMissing if short else _S.BadTooManyArguments)
        sub = self._iserver.subscription_service.subscriptions.get(wanted[0])
        if sub is None or sub.session_id != call.session.session_id:
            return _status(_S.BadSubscriptionIdInvalid)
        service = sub.monitored_item_srv
        items = [
            (notifier, mid)
            for notifier, mids in service._monitored_events.items()
            for mid in mids
            if not two or mid == wanted[1]
        ]
        if two and not items:
            return _status(_S.BadMonitoredItemIdInvalid)
        retained = self.retained()
        for notifier, mid in items:
            await self._bracket(service, event_objects.RefreshStartEvent(), notifier, mid)
            for cond in retained:
                if notifier in (SERVER, ua.NodeId(cond.machine_id, self.idx)):
                    event = self.event_of(cond)
                    event.emitting_node = notifier
                    await service._trigger_event(event, mid)
            await self._bracket(service, event_objects.RefreshEndEvent(), notifier, mid)
        return ua.CallMethodResult()

    async def _bracket(self, service: Any, event: Any, notifier: ua.NodeId, mid: int) -> None:
        """RefreshStart or RefreshEnd to one item, past its where clause (a filter for alarms
        must not hide where the refresh begins and ends)."""
        item = service._monitored_items.get(mid)
        if item is None:
            return
        now = datetime.now(UTC)
        event.EventId = uuid.uuid4().bytes
        event.SourceNode, event.SourceName = SERVER, "Server"
        event.Time = event.ReceiveTime = now
        event.emitting_node = notifier
        fields = event.to_event_fields(item.filter.SelectClauses)
        notice = ua.EventFieldList(ClientHandle=item.client_handle, EventFields=fields)
        await service.isub.enqueue_event(mid, notice, item.queue_size)


def _status(code: int) -> ua.CallMethodResult:
    return ua.CallMethodResult(StatusCode=ua.StatusCode(code))
