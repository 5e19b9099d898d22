"""The OPC UA address space: Objects → Machines → one object per machine, its variables kept
up to date from the bus, its events fired on it (and on the Server object, for event views).

Node ids are strings a SCADA can type: `ns=<gateway ns>;s=<machine>/<path>` (e.g. `m1/State`,
`m1/Diagnostics/CycleTimeP99`, `m1/IO/DI/estop`). A value is written only when it changed, with
the machine's time as its source timestamp.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.manage_nodes import delete_nodes

from rider.gateway.alarms import Alarm
from rider.gateway.parking import Parking
from rider.gateway.variables import (
    AXIS_VARS,
    DIAG_VARS,
    STATUS_VARS,
    UNITS_URI,
    V,
    Var,
    io_var,
)
from schema.axes import AxisRecord
from schema.diag import CycleDiag
from schema.io import IoValue
from schema.status import Status

log = logging.getLogger(__name__)

NAMESPACE = "urn:ride-machine:gateway"
_GONE = ua.StatusCode(ua.StatusCodes.BadNoCommunication)
_UNKNOWN = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)


_ZERO: dict[ua.VariantType, object] = {V.Boolean: False, V.String: "", V.Double: 0.0}


def _time(t: float) -> datetime:
    return datetime.fromtimestamp(t, UTC)


class MachineNode:
    """One machine's object: its variables by path, their last values, its event generator."""

    def __init__(self, space: Space, machine_id: str, obj: Node) -> None:
        self.space = space
        self.machine_id = machine_id
        self.obj = obj
        self.nodes: dict[str, tuple[ua.NodeId, Var]] = {}
        self.last: dict[str, Any] = {}
        self.folders: dict[str, Node] = {}
        self.events: Any = None
        self.properties: list[ua.NodeId] = []
        self.methods: list[ua.NodeId] = []

    def value_ids(self) -> list[ua.NodeId]:
        """Every node of the machine with a value a client may monitor."""
        return [nid for nid, _var in self.nodes.values()] + self.properties

    def nodeid(self, path: str) -> ua.NodeId:
        return ua.NodeId(f"{self.machine_id}/{path}", self.space.idx)

    async def add_vars(self, parent: Node, prefix: str, table: tuple[Var, ...]) -> None:
        for var in table:
            await self.add_var(parent, prefix + var.name, var)

    async def add_var(self, parent: Node, path: str, var: Var) -> None:
        nid = self.nodeid(path)
        initial = ua.Variant(_ZERO.get(var.vtype, 0), var.vtype)  # shown Bad until written
        node = await parent.add_variable(nid, self.space.qname(var.name), initial, var.vtype)
        if var.doc:
            await node.write_attribute(
                ua.AttributeIds.Description, ua.DataValue(ua.LocalizedText(var.doc))
            )
        if var.unit is not None:
            eu = ua.EUInformation(
                NamespaceUri=UNITS_URI,
                UnitId=var.unit.unit_id,
                DisplayName=ua.LocalizedText(var.unit.symbol),
                Description=ua.LocalizedText(var.unit.description),
            )
            prop = await node.add_property(self.space.idx, "EngineeringUnits", eu)
            self.properties.append(prop.nodeid)
            self.space.parking.unpark([prop.nodeid])
        self.space.parking.unpark([nid])  # a client's items from before it was forgotten
        # A Bad quality until the machine says: never a made-up zero.
        await self.space.server.write_attribute_value(nid, ua.DataValue(StatusCode=_UNKNOWN))
        self.nodes[path] = (nid, var)

    async def folder(self, path: str) -> Node:
        """`path`'s folder (made on first use: IO names come from the machine's config)."""
        found = self.folders.get(path)
        if found is None:
            parent_path, _, name = path.rpartition("/")
            parent = await self.folder(parent_path) if parent_path else self.obj
            found = await parent.add_folder(self.nodeid(path), self.space.qname(name))
            self.folders[path] = found
        return found

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
            path = f"IO/{update.kind.value.upper()}/{update.name}"
            if path not in self.nodes:
                await self.add_var(await self.folder(path.rpartition("/")[0]), path, io_var(update))
            await self.write(path, update, update.time, snapshot)
        else:
            prefix = f"Axes/{update.axis}/"
            if prefix + AXIS_VARS[0].name not in self.nodes:
                await self.add_vars(await self.folder(prefix.rstrip("/")), prefix, AXIS_VARS)
            for var in AXIS_VARS:
                await self.write(prefix + var.name, update, update.time, snapshot)

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
        self.folder: Node | None = None
        self.event_type: Node | None = None
        self.server_events: Any = None
        self.model_events: Any = None
        self.parking = Parking(server.iserver.aspace)

    def qname(self, name: str) -> ua.QualifiedName:
        """A browse name in the gateway's namespace."""
        return ua.QualifiedName(name, self.idx)

    async def setup(self) -> None:
        """The namespace, the `Machines` folder and the machine event type."""
        self.idx = await self.server.register_namespace(NAMESPACE)
        objects = self.server.nodes.objects
        machines = ua.NodeId("Machines", self.idx)
        self.folder = await objects.add_folder(machines, self.qname("Machines"))
        self.event_type = await self.server.create_custom_event_type(
            self.idx,
            "MachineEventType",
            ua.ObjectIds.BaseEventType,
            [("Machine", V.String), ("Kind", V.String), ("Code", V.String)],
        )
        self.server_events = await self.server.get_event_generator(self.event_type)
        self.model_events = await self.server.get_event_generator(
            ua.ObjectIds.GeneralModelChangeEventType, ua.ObjectIds.Server
        )
        self.model_events.event.data_types["Changes"] = V.ExtensionObject

    async def model_changed(self, machine: ua.NodeId, added: bool) -> None:
        """A `GeneralModelChangeEvent` on the Server object: a machine's object added under
        `Machines`, or deleted from it (OPC UA Part 3, 9.32)."""
        verbs = ua.ModelChangeStructureVerbMask
        assert self.folder is not None
        node_verb = verbs.NodeAdded if added else verbs.NodeDeleted
        ref_verb = verbs.ReferenceAdded if added else verbs.ReferenceDeleted
        base = ua.NodeId(ua.ObjectIds.BaseObjectType)
        folder = ua.NodeId(ua.ObjectIds.FolderType)
        self.model_events.event.Changes = [
            ua.ModelChangeStructureDataType(machine, base, int(node_verb)),
            ua.ModelChangeStructureDataType(self.folder.nodeid, folder, int(ref_verb)),
        ]
        what = "added" if added else "deleted"
        await self.model_events.trigger(message=f"machine {machine.Identifier} {what}")

    async def add(self, machine_id: str) -> MachineNode:
        """The machine's object with its status and diagnostics variables (Bad until heard)."""
        assert self.folder is not None
        obj = await self.folder.add_object(ua.NodeId(machine_id, self.idx), self.qname(machine_id))
        node = MachineNode(self, machine_id, obj)
        alive = Var("Alive", V.Boolean, bool, doc="the machine's liveliness token is present")
        await node.add_var(obj, "Alive", alive)
        await node.add_vars(obj, "", STATUS_VARS)
        await node.add_vars(await node.folder("Diagnostics"), "Diagnostics/", DIAG_VARS)
        node.events = await self.server.get_event_generator(self.event_type, obj)
        self.machines[machine_id] = node
        await node.presence(True)
        await self.model_changed(obj.nodeid, added=True)
        log.info("event=opcua_machine_added machine=%s", machine_id)
        return node

    async def remove(self, machine_id: str) -> None:
        node = self.machines.pop(machine_id, None)
        if node is None:
            return
        # Without `delete_target_references`: asyncua would scan the whole address space for
        # references to each deleted node, blocking the loop for seconds (long enough for its
        # own session watchdog to close idle clients). The only reference from outside the
        # machine's subtree is the folder's, removed here.
        assert self.folder is not None
        parked = await self.parking.park(node.value_ids())
        await self.folder.delete_reference(node.obj, ua.ObjectIds.Organizes, bidirectional=False)
        await delete_nodes(
            self.server.iserver.isession, [node.obj], recursive=True, delete_target_references=False
        )
        await self.model_changed(node.obj.nodeid, added=False)
        log.info("event=opcua_machine_removed machine=%s parked_items=%d", machine_id, parked)
