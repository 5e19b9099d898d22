"""`RideMachineType` and `RideAxisType`: what every machine's object is, declared once as data
and built two ways — the ObjectTypes with their instance declarations (ModellingRule
Mandatory), and each machine's instance of them — with string node ids a SCADA can type and
that never depend on which machine came first: `RideMachineType/<path>` for the type,
`<machine>/<path>` for an instance, `…/EngineeringUnits`, `…/EURange`, `…/InputArguments`
for their properties.

Nodes are added in one AddNodes call per machine (asyncua's own instantiation browses the type
node by node, and numbers the properties it makes in the order machines join).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from asyncua import ua

from ride_machine.schema.commands import Command

from .variables import (
    AXES,
    DIAG_VARS,
    STATUS_VARS,
    UNITS_URI,
    V,
    Var,
    axis_vars,
)

OWN = "gateway."
"""The gateway's own node ids start so: a machine id never has a dot, so no machine's object
(`<id>`, `<id>/<path>`) can be one of them (a machine called `Machines` is a machine)."""
MACHINE_TYPE = f"{OWN}RideMachineType"
AXIS_TYPE = f"{OWN}RideAxisType"
MACHINES = f"{OWN}Machines"
EVENT_TYPE = f"{OWN}MachineEventType"
_I = ua.ObjectIds
_ID = ua.NodeId

METHODS: tuple[Command, ...] = (
    Command.HOME,
    Command.CALIBRATE_TILT,
    Command.CALIBRATE_ROTATE,
    Command.START,
    Command.PAUSE,
    Command.RESUME,
    Command.STOP,
)
"""The commands a SCADA may call, by their own names."""

OUTPUTS = (
    ("Code", "the reply code (RESP_…) or, refused, the machine's error code"),
    ("Message", "empty when accepted; why, when refused"),
    ("TransactionId", "the command's transaction (its completion notice's key)"),
    ("State", "the machine's state after the command"),
)
SESSION_ARG = ("Session", 'JSON, e.g. {"name": "s", "steps": [...]}; "" = default')
_ZERO: dict[ua.VariantType, object] = {V.Boolean: False, V.String: "", V.Double: 0.0}
ALIVE = Var("Alive", V.Boolean, bool, doc="the machine's liveliness token is present")


@dataclass(frozen=True)
class Decl:
    """One node of the machine's shape: a variable (`var`), a folder or object (children), or
    a method (`command`)."""

    name: str
    var: Var | None = None
    children: tuple[Decl, ...] = ()
    type_def: int | str = _I.FolderType
    """A standard type's number, or one of the gateway's own type ids."""
    command: Command | None = None

    @property
    def node_class(self) -> ua.NodeClass:
        if self.var is not None:
            return ua.NodeClass.Variable
        return ua.NodeClass.Method if self.command is not None else ua.NodeClass.Object


def _vars(table: tuple[Var, ...]) -> tuple[Decl, ...]:
    return tuple(Decl(v.name, var=v) for v in table)


def machine_shape() -> tuple[Decl, ...]:
    """A machine's object's children, in browse order."""
    return (
        Decl("Alive", var=ALIVE),
        *_vars(STATUS_VARS),
        Decl("Diagnostics", children=_vars(DIAG_VARS)),
        Decl("IO", children=tuple(Decl(k) for k in ("DI", "RO", "AI"))),
        Decl("Axes", children=tuple(axis_shape(a) for a in AXES)),
        *(Decl(c.value, command=c) for c in METHODS),
    )


def axis_shape(axis: str) -> Decl:
    return Decl(axis, children=_vars(axis_vars(axis)), type_def=AXIS_TYPE)


@dataclass
class Built:
    """What building a shape adds: the nodes (in order), the references after them, and the
    node ids of everything with a value, of each variable by path, of each method."""

    nodes: list[ua.AddNodesItem] = field(default_factory=list)
    references: list[ua.AddReferencesItem] = field(default_factory=list)
    values: dict[str, tuple[ua.NodeId, Var]] = field(default_factory=dict)
    """Variables by path (`State`, `Axes/tilt/Velocity`): the ones the machine's data fills."""
    properties: list[ua.NodeId] = field(default_factory=list)
    methods: dict[Command, ua.NodeId] = field(default_factory=dict)


@dataclass(frozen=True)
class Builder:
    """Adds a shape under `prefix` (a machine id, or a type's name) in namespace `idx`;
    `declarations`: the type's own nodes, each with ModellingRule Mandatory."""

    idx: int
    prefix: str
    declarations: bool = False

    def nid(self, path: str) -> ua.NodeId:
        return _ID(f"{self.prefix}/{path}", self.idx)

    def build(
        self, parent: ua.NodeId, shape: tuple[Decl, ...], into: Built, path: str = ""
    ) -> Built:
        """`shape`'s nodes under `parent` (at `path`, `Axes/` for instance), added to `into`."""
        for decl in shape:
            here = f"{path}{decl.name}"
            nid = self.nid(here)
            into.nodes.append(self._item(parent, nid, decl))
            self._rule(nid, into)
            if decl.var is not None:
                into.values[here] = (nid, decl.var)
                for prop in self._var_properties(nid, decl.var):
                    into.nodes.append(prop)
                    self._rule(prop.RequestedNewNodeId, into)
                    into.properties.append(prop.RequestedNewNodeId)
            elif decl.command is not None:
                into.methods[decl.command] = nid
                for prop in _arguments(nid, decl.command):
                    into.nodes.append(prop)
                    self._rule(prop.RequestedNewNodeId, into)
                    into.properties.append(prop.RequestedNewNodeId)
            self.build(nid, decl.children, into, here + "/")
        return into

    def _item(self, parent: ua.NodeId, nid: ua.NodeId, decl: Decl) -> ua.AddNodesItem:
        item = ua.AddNodesItem(
            RequestedNewNodeId=nid,
            BrowseName=ua.QualifiedName(decl.name, self.idx),
            ParentNodeId=parent,
            ReferenceTypeId=_ID(_I.HasComponent),
            NodeClass=decl.node_class,
        )
        if decl.var is not None:
            item.TypeDefinition = _ID(_variable_type(decl.var))
            item.NodeAttributes = _variable(decl.var)
        elif decl.command is not None:
            item.NodeAttributes = ua.MethodAttributes(
                DisplayName=ua.LocalizedText(decl.name),
                Description=ua.LocalizedText(f"the machine's {decl.name} command"),
                Executable=True,
                UserExecutable=True,
            )
        else:
            item.TypeDefinition = type_id(decl.type_def, self.idx)
            item.NodeAttributes = ua.ObjectAttributes(DisplayName=ua.LocalizedText(decl.name))
        return item

    def _rule(self, nid: ua.NodeId, into: Built) -> None:
        if self.declarations:
            into.references.append(
                ua.AddReferencesItem(
                    SourceNodeId=nid,
                    ReferenceTypeId=_ID(_I.HasModellingRule),
                    IsForward=True,
                    TargetNodeId=_ID(_I.ModellingRule_Mandatory),
                    TargetNodeClass=ua.NodeClass.Object,
                )
            )

    def _var_properties(self, nid: ua.NodeId, var: Var) -> Iterator[ua.AddNodesItem]:
        if var.unit is not None:
            eu = ua.EUInformation(
                NamespaceUri=UNITS_URI,
                UnitId=var.unit.unit_id,
                DisplayName=ua.LocalizedText(var.unit.symbol),
                Description=ua.LocalizedText(var.unit.description),
            )
            yield _property(nid, "EngineeringUnits", eu, _I.EUInformation)
        if var.eurange is not None:
            low, high = var.eurange
            yield _property(nid, "EURange", ua.Range(Low=low, High=high), _I.Range)


def type_id(type_def: int | str, idx: int) -> ua.NodeId:
    return _ID(type_def, idx) if isinstance(type_def, str) else _ID(type_def)


def object_type(idx: int, name: str, base: int, doc: str) -> ua.AddNodesItem:
    """An ObjectType of the gateway's, subtype of `base`."""
    return ua.AddNodesItem(
        RequestedNewNodeId=_ID(name, idx),
        BrowseName=ua.QualifiedName(name.removeprefix(OWN), idx),
        ParentNodeId=_ID(base),
        ReferenceTypeId=_ID(_I.HasSubtype),
        NodeClass=ua.NodeClass.ObjectType,
        NodeAttributes=ua.ObjectTypeAttributes(
            DisplayName=ua.LocalizedText(name.removeprefix(OWN)),
            Description=ua.LocalizedText(doc),
            IsAbstract=False,
        ),
    )


def types(idx: int) -> Built:
    """`RideAxisType` and `RideMachineType` with their instance declarations."""
    built = Built()
    axis = object_type(idx, AXIS_TYPE, _I.BaseObjectType, "one axis of a ride: position, speed")
    built.nodes.append(axis)
    Builder(idx, AXIS_TYPE, declarations=True).build(
        axis.RequestedNewNodeId, _vars(axis_vars("*")), built
    )
    machine = object_type(
        idx, MACHINE_TYPE, _I.BaseObjectType, "a two-axis ride machine, as rider gateway shows it"
    )
    built.nodes.append(machine)
    Builder(idx, MACHINE_TYPE, declarations=True).build(
        machine.RequestedNewNodeId, machine_shape(), built
    )
    return built


def instance(idx: int, machine_id: str, parent: ua.NodeId) -> Built:
    """One machine's object (an event notifier, of `RideMachineType`) and all its nodes."""
    built = Built()
    obj = ua.AddNodesItem(
        RequestedNewNodeId=_ID(machine_id, idx),
        BrowseName=ua.QualifiedName(machine_id, idx),
        ParentNodeId=parent,
        ReferenceTypeId=_ID(_I.Organizes),
        NodeClass=ua.NodeClass.Object,
        TypeDefinition=_ID(MACHINE_TYPE, idx),
        NodeAttributes=ua.ObjectAttributes(
            DisplayName=ua.LocalizedText(machine_id),
            EventNotifier=ua.EventNotifier.SubscribeToEvents.mask,
        ),
    )
    built.nodes.append(obj)
    return Builder(idx, machine_id).build(obj.RequestedNewNodeId, machine_shape(), built)


def _variable_type(var: Var) -> Any:
    if var.eurange is not None:
        return _I.AnalogItemType
    if var.unit is not None:
        return _I.AnalogUnitType
    return _I.BaseDataVariableType


def _variable(var: Var) -> ua.VariableAttributes:
    read = ua.AccessLevel.CurrentRead.mask
    return ua.VariableAttributes(
        DisplayName=ua.LocalizedText(var.name),
        Description=ua.LocalizedText(var.doc or var.name),
        Value=ua.Variant(_ZERO.get(var.vtype, 0), var.vtype),  # written Bad before anyone reads
        DataType=_ID(var.vtype.value),
        ValueRank=ua.ValueRank.Scalar,
        AccessLevel=read,
        UserAccessLevel=read,
        MinimumSamplingInterval=0.0,  # pushed as the machine publishes, never polled
    )


def _property(parent: ua.NodeId, name: str, value: object, datatype: int) -> ua.AddNodesItem:
    read = ua.AccessLevel.CurrentRead.mask
    variant = ua.Variant(value, ua.VariantType.ExtensionObject)
    return ua.AddNodesItem(
        RequestedNewNodeId=_ID(f"{parent.Identifier}/{name}", parent.NamespaceIndex),
        BrowseName=ua.QualifiedName(name, 0),
        ParentNodeId=parent,
        ReferenceTypeId=_ID(_I.HasProperty),
        NodeClass=ua.NodeClass.Variable,
        TypeDefinition=_ID(_I.PropertyType),
        NodeAttributes=ua.VariableAttributes(
            DisplayName=ua.LocalizedText(name),
            Value=variant,
            DataType=_ID(datatype),
            ValueRank=ua.ValueRank.Scalar,
            AccessLevel=read,
            UserAccessLevel=read,
        ),
    )


def _arguments(method: ua.NodeId, command: Command) -> Iterator[ua.AddNodesItem]:
    """A method's `InputArguments` (Start's session) and `OutputArguments` properties."""
    if command is Command.START:
        yield _argument_list(method, "InputArguments", [SESSION_ARG])
    yield _argument_list(method, "OutputArguments", list(OUTPUTS))


def _argument_list(method: ua.NodeId, name: str, args: list[tuple[str, str]]) -> ua.AddNodesItem:
    values = [
        ua.Argument(
            Name=arg,
            DataType=_ID(_I.String),
            ValueRank=ua.ValueRank.Scalar,
            Description=ua.LocalizedText(doc),
        )
        for arg, doc in args
    ]
    item = _property(method, name, values, _I.Argument)
    attrs = item.NodeAttributes
    attrs.Value = ua.Variant(values, ua.VariantType.ExtensionObject)
    attrs.ValueRank = ua.ValueRank.OneDimension
    attrs.ArrayDimensions = [len(values)]
    return item


EVENT_FIELDS = (
    ("Machine", "the machine's id"),
    ("Kind", "the machine's event kind (estop_pressed, fault_raised, …)"),
    ("Code", "its code: ESTOP, the fault code, the outcome"),
)


def event_type(idx: int) -> Built:
    """`MachineEventType`: a BaseEventType with the fields `Machine`, `Kind` and `Code`."""
    built = Built()
    etype = object_type(idx, EVENT_TYPE, _I.BaseEventType, "an event of a machine's history")
    built.nodes.append(etype)
    fields = tuple(Decl(name, var=Var(name, V.String, str, doc=doc)) for name, doc in EVENT_FIELDS)
    builder = Builder(idx, EVENT_TYPE, declarations=True)
    builder.build(etype.RequestedNewNodeId, fields, built)
    for item in built.nodes[1:]:
        item.ReferenceTypeId = _ID(_I.HasProperty)
        item.TypeDefinition = _ID(_I.PropertyType)
        item.BrowseName = ua.QualifiedName(item.BrowseName.Name, idx)
    return built
