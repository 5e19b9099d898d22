"""The OPC UA address space: Objects → Machines → one object per machine, of
`RideMachineType` (rider/gateway/typemodel.py), its variables kept up to date from the bus, its
events fired on it (and on the Server object, for event views).

Node ids are strings a SCADA can type: `ns=<gateway ns>;s=<machine>/<path>` (e.g. `m1/State`,
`m1/Diagnostics/CycleTimeP99`, `m1/IO/DI/estop`), the same on every start and whatever order
the machines join in. A value is written only when it changed, with the machine's time as its
source timestamp.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.manage_nodes import delete_nodes

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.commands import Command
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import Status

from .alarms import Alarm
from .parking import Parking
from .typemodel import (
    MACHINE_TYPE,
    MACHINES,
    Builder,
    Built,
    Decl,
    axis_shape,
    event_type,
    instance,
    types,
)
from .variables import DIAG_VARS, STATUS_VARS, V, io_var

log = logging.getLogger(__name__)

NAMESPACE = "urn:ride-machine:gateway"
_GONE = ua.StatusCode(ua.StatusCodes.BadNoCommunication)
_UNKNOWN = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)


def _time(t: float) -> datetime:
    return datetime.fromtimestamp(t, UTC)


class MachineNode:
    """One machine's object: its variables by path, their last values, its methods, its event
    generator."""

    def __init__(self, space: Space, machine_id: str, built: Built) -> None:
        self.space = space
        self.machine_id = machine_id
        self.obj = Node(space.server.iserver.isession, built.nodes[0].RequestedNewNodeId)
        self.nodes: dict[str, tuple[ua.NodeId, Any]] = dict(built.values)
        self.properties: list[ua.NodeId] = list(built.properties)
        self.methods: dict[Command, ua.NodeId] = dict(built.methods)
        self.last: dict[str, Any] = {}
        self.events: Any = None

    def value_ids(self) -> list[ua.NodeId]:
        """Every node of the machine with a value a client may monitor."""
        return [nid for nid, _var in self.nodes.values()] + self.properties

    def nodeid(self, path: str) -> ua.NodeId:
        return ua.NodeId(f"{self.machine_id}/{path}", self.space.idx)

    async def grow(self, under: str, shape: tuple[Decl, ...]) -> None:
        """Nodes the type does not declare, under `under`: a machine's IO (its names come from
        its config) or an axis of another name."""
        built = Builder(self.space.idx, self.machine_id).build(
            self.nodeid(under), shape, Built(), f"{under}/"
        )
        await self.space.add_built(built)
        self.nodes.update(built.values)
        self.properties += built.properties

    async def write(self, path: str, model: Any, when: float, snapshot: bool = False) -> None:
        """The value `path` reads from `model` (the machine's time `when` as its source
        timestamp), when it changed; a snapshot only fills a value not written since the
        machine (re)appeared."""
        nid, var = self.nodes[path]
        value = var.read(model)
        if path in self.last and (snapshot or self.last[path] == value):
            return
        self.last[path] = value
        source, now = _time(when), datetime.now(UTC)
        if value is None:
            dv = ua.DataValue(StatusCode=_UNKNOWN, SourceTimestamp=source, ServerTimestamp=now)
        else:
            variant = ua.Variant(value, var.vtype)
            dv = ua.DataValue(variant, SourceTimestamp=source, ServerTimestamp=now)
        await self.space.server.write_attribute_value(nid, dv)

    async def update(
        self, update: Status | CycleDiag | IoValue | AxisRecord, snapshot: bool = False
    ) -> None:
        """Write what a publication (or a snapshot read) carries."""
        if isinstance(update, Status):
            for var in STATUS_VARS:
                await self.write(var.name, update, update.time, snapshot)
        elif isinstance(update, CycleDiag):
            for var in DIAG_VARS:
                await self.write(f"Diagnostics/{var.name}", update, update.time, snapshot)
        elif isinstance(update, IoValue):
            folder = f"IO/{update.kind.value.upper()}"
            path = f"{folder}/{update.name}"
            if path not in self.nodes:
                await self.grow(folder, (Decl(update.name, var=io_var(update)),))
            await self.write(path, update, update.time, snapshot)
        else:
            shape = axis_shape(update.axis)
            prefix = f"Axes/{update.axis}/"
            if prefix + shape.children[0].name not in self.nodes:
                await self.grow("Axes", (shape,))
            for decl in shape.children:
                await self.write(prefix + decl.name, update, update.time, snapshot)

    async def presence(self, alive: bool) -> None:
        """`Alive` follows the token (the gateway's time of the change as its source
        timestamp); a machine gone leaves every other value Bad (no communication) until it
        is back and publishes, or answers the gateway's reads, again."""
        now = datetime.now(UTC)
        alive_dv = ua.DataValue(
            ua.Variant(alive, V.Boolean), SourceTimestamp=now, ServerTimestamp=now
        )
        await self.space.server.write_attribute_value(self.nodeid("Alive"), alive_dv)
        if alive:
            return
        self.last.clear()
        gone = ua.DataValue(StatusCode=_GONE, SourceTimestamp=now, ServerTimestamp=now)
        for path, (nid, _var) in self.nodes.items():
            if path != "Alive":
                await self.space.server.write_attribute_value(nid, gone)

    async def fire(self, alarm: Alarm, when: float) -> None:
        """The machine's event on its object, and on the Server object for event views."""
        for gen in (self.events, self.space.server_events):
            ev = gen.event
            ev.SourceNode = self.obj.nodeid
            ev.SourceName = self.machine_id
            ev.Severity = int(alarm.severity)
            ev.Kind = alarm.kind
            ev.Code = alarm.code
            ev.Machine = self.machine_id
            await gen.trigger(time_attr=_time(when), message=alarm.message)


class Space:
    """The gateway's part of the address space; `add`/`remove` follow the machines."""

    def __init__(self, server: Server) -> None:
        self.server = server
        self.idx = 0
        self.machines: dict[str, MachineNode] = {}
        self.folder: ua.NodeId | None = None
        self.event_type: ua.NodeId | None = None
        self.server_events: Any = None
        self.model_events: Any = None
        self.parking = Parking(server.iserver.aspace)

    async def setup(self) -> None:
        """The namespace, the types, the `Machines` folder and the machine event type."""
        self.idx = await self.server.register_namespace(NAMESPACE)
        await self.add_built(types(self.idx), initial=False)
        events = event_type(self.idx)
        await self.add_built(events, initial=False)
        self.event_type = events.nodes[0].RequestedNewNodeId
        folder = ua.AddNodesItem(
            RequestedNewNodeId=ua.NodeId(MACHINES, self.idx),
            BrowseName=ua.QualifiedName("Machines", self.idx),
            ParentNodeId=ua.NodeId(ua.ObjectIds.ObjectsFolder),
            ReferenceTypeId=ua.NodeId(ua.ObjectIds.Organizes),
            NodeClass=ua.NodeClass.Object,
            TypeDefinition=ua.NodeId(ua.ObjectIds.FolderType),
            NodeAttributes=ua.ObjectAttributes(DisplayName=ua.LocalizedText("Machines")),
        )
        await self.add_built(Built(nodes=[folder]), initial=False)
        self.folder = folder.RequestedNewNodeId
        self.server_events = await self.server.get_event_generator(self.event_type)
        self.model_events = await self.server.get_event_generator(
            ua.ObjectIds.GeneralModelChangeEventType, ua.ObjectIds.Server
        )
        self.model_events.event.data_types["Changes"] = V.ExtensionObject

    async def add_built(self, built: Built, initial: bool = True) -> None:
        """Add what a build made; give back the monitored items parked on its nodes (a machine
        that returns), then (`initial`) mark each value Bad until the machine says it."""
        isession = self.server.iserver.isession
        for result in await isession.add_nodes(built.nodes):
            result.StatusCode.check()
        for status in await isession.add_references(built.references):
            status.check()
        if not initial:
            return
        self.parking.unpark([nid for nid, _ in built.values.values()] + built.properties)
        unknown = ua.DataValue(StatusCode=_UNKNOWN, ServerTimestamp=datetime.now(UTC))
        for nid, _var in built.values.values():
            await self.server.write_attribute_value(nid, unknown)

    async def model_changed(self, machine: ua.NodeId, added: bool) -> None:
        """A `GeneralModelChangeEvent` on the Server object: a machine's object added under
        `Machines`, or deleted from it (OPC UA Part 3, 9.32)."""
        verbs = ua.ModelChangeStructureVerbMask
        assert self.folder is not None
        node_verb = verbs.NodeAdded if added else verbs.NodeDeleted
        ref_verb = verbs.ReferenceAdded if added else verbs.ReferenceDeleted
        machine_type = ua.NodeId(MACHINE_TYPE, self.idx)
        folder = ua.NodeId(ua.ObjectIds.FolderType)
        self.model_events.event.Changes = [
            ua.ModelChangeStructureDataType(machine, machine_type, int(node_verb)),
            ua.ModelChangeStructureDataType(self.folder, folder, int(ref_verb)),
        ]
        what = "added" if added else "deleted"
        await self.model_events.trigger(message=f"machine {machine.Identifier} {what}")

    async def add(self, machine_id: str) -> MachineNode:
        """The machine's object, of `RideMachineType`, with all its nodes (Bad until heard)."""
        assert self.folder is not None
        built = instance(self.idx, machine_id, self.folder)
        await self.add_built(built)
        node = MachineNode(self, machine_id, built)
        node.events = await self.server.get_event_generator(self.event_type, node.obj)
        self.machines[machine_id] = node
        await node.presence(True)
        await self.model_changed(node.obj.nodeid, added=True)
        log.info("event=opcua_machine_added machine=%s", machine_id)
        return node

    async def remove(self, machine_id: str) -> None:
        node = self.machines.pop(machine_id, None)
        if node is None:
            return
        assert self.folder is not None
        parked = await self.parking.park(node.value_ids())
        # Without `delete_target_references`: asyncua would scan the whole address space for
        # references to each deleted node, blocking the loop for seconds (long enough for its
        # own session watchdog to close idle clients). The only reference from outside the
        # machine's subtree is the folder's, removed here.
        folder = Node(self.server.iserver.isession, self.folder)
        await folder.delete_reference(node.obj, ua.ObjectIds.Organizes, bidirectional=False)
        await delete_nodes(
            self.server.iserver.isession, [node.obj], recursive=True, delete_target_references=False
        )
        await self.model_changed(node.obj.nodeid, added=False)
        log.info("event=opcua_machine_removed machine=%s parked_items=%d", machine_id, parked)
