"""The Call service as OPC UA Part 4 (5.11.2) says: a method runs only on an object it belongs
to, each wrong call gets its own status code, and who may call what is decided per method.

asyncua's own Call service ran any method on any object (ObjectId ignored: `Call(m3, m4/Stop)`
stopped m4), answered an unknown method `BadNodeIdInvalid` and a variable called as a method
`BadNothingToDo`, and logged a failed call's whole request, arguments included. Here:

- the object must exist (`BadNodeIdUnknown`) and be an object or an object type
  (`BadNodeIdInvalid`); the method must exist and be a method of that object: its component,
  or a component of its type or a supertype (the type's method then runs as the instance's
  own of the same name), else `BadMethodInvalid`;
- more input arguments than `MAX_ARGUMENTS`, or a string or byte string longer than
  `MAX_ARGUMENT_BYTES`, is refused before anything runs (`BadTooManyArguments`,
  `BadOutOfRange`), and no argument is ever logged;
- each method has a role: a machine's commands and `Acknowledge` need the operator
  (`BadUserAccessDenied` otherwise), `ConditionRefresh` and `GetMonitoredItems` are for any
  session that may subscribe, and no other standard method may be called.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any

from asyncua import Node, ua
from asyncua.server.internal_session import InternalSession

from .security import Caller

log = logging.getLogger(__name__)

MAX_ARGUMENTS = 8
"""More input arguments than any method here takes: refused unread."""
MAX_ARGUMENT_BYTES = 16 * 1024
"""The longest String or ByteString argument (a session of 100 steps is about 8 KB of JSON);
also the server's MaxStringLength."""

_S = ua.StatusCodes
TOO_MANY: int = _S.BadTooManyArguments
TOO_LONG: int = _S.BadOutOfRange
_HAS_COMPONENT = ua.ObjectIds.HasComponent


class Role(Enum):
    """Who may call a method."""

    SESSION = "any session"
    OPERATOR = "operator"


@dataclass(frozen=True)
class Invocation:
    """One call as the handler sees it: who, on which object, with what."""

    caller: Caller
    session: InternalSession
    object_id: ua.NodeId
    method_id: ua.NodeId
    arguments: list[ua.Variant]


Handler = Callable[[Invocation], Awaitable[ua.CallMethodResult]]


class Calls:
    """Method handlers by method node id, and the checks every call passes first."""

    def __init__(self, isession: InternalSession) -> None:
        self._isession = isession
        self._handlers: dict[ua.NodeId, tuple[Role, Handler]] = {}
        self.virtual: Callable[[ua.NodeId], bool] = lambda _object_id: False
        """Whether an object id names an object that is no node (a condition's ConditionId,
        rider/gateway/alarmlist.py): a bound method called on it runs."""

    def bind(self, method: ua.NodeId, role: Role, handler: Handler) -> None:
        self._handlers[method] = (role, handler)

    def unbind(self, method: ua.NodeId) -> None:
        self._handlers.pop(method, None)

    def role(self, method: ua.NodeId) -> Role | None:
        bound = self._handlers.get(method)
        return bound[0] if bound is not None else None

    async def call(
        self, session: InternalSession, requests: list[ua.CallMethodRequest]
    ) -> list[ua.CallMethodResult]:
        return [await self._one(session, request) for request in requests]

    async def _one(
        self, session: InternalSession, request: ua.CallMethodRequest
    ) -> ua.CallMethodResult:
        args = list(request.InputArguments or [])
        status = _too_much(args)
        method: ua.NodeId | None = None
        if status is None:
            method, status = await self._resolve(request.ObjectId, request.MethodId)
        if status is None and method is not None:
            role, handler = self._handlers[method]
            caller = session.user
            if not isinstance(caller, Caller) or (role is Role.OPERATOR and not caller.operator):
                status = _S.BadUserAccessDenied
        if status is not None or method is None:
            status = status or _S.BadMethodInvalid
            log.info(
                # %r: the ids are the client's, a newline in one would forge a log line.
                "event=opcua_call_refused object=%r method=%r status=%s arguments=%d",
                request.ObjectId.to_string(),
                request.MethodId.to_string(),
                ua.StatusCode(status).name,
                len(args),
            )
            return refused(status, len(args))
        call = Invocation(caller, session, request.ObjectId, method, args)
        try:
            result = await handler(call)
        except Exception as exc:  # noqa: BLE001 - a handler's bug: said, without the arguments
            log.error(
                "event=opcua_call_failed object=%r method=%r error=%s",
                request.ObjectId.to_string(),
                method.to_string(),
                type(exc).__name__,
            )
            return refused(_S.BadInternalError, len(args))
        while len(result.InputArgumentResults) < len(args):
            result.InputArgumentResults.append(ua.StatusCode())
        return result

    async def _resolve(
        self, object_id: ua.NodeId, method_id: ua.NodeId
    ) -> tuple[ua.NodeId | None, int | None]:
        """The bound method for `method_id` called on `object_id`, or a status."""
        if method_id in self._handlers and self.virtual(object_id):
            return method_id, None
        obj = Node(self._isession, object_id)
        obj_class = await _node_class(obj)
        if obj_class is None:
            return None, _S.BadNodeIdUnknown
        if obj_class not in (ua.NodeClass.Object, ua.NodeClass.ObjectType):
            return None, _S.BadNodeIdInvalid
        if await _node_class(Node(self._isession, method_id)) is not ua.NodeClass.Method:
            return None, _S.BadMethodInvalid
        own = await _components(obj)
        if method_id in own:
            return self._bound(method_id)
        for owner in await _types_of(obj, obj_class):
            declared = await _components(owner)
            if method_id not in declared:
                continue
            if method_id in self._handlers:  # the type's method itself (Acknowledge)
                return method_id, None
            # The instance's own method of that name runs (a machine's Home).
            same = [nid for nid, name in own.items() if name == declared[method_id]]
            return self._bound(same[0]) if same else (None, _S.BadMethodInvalid)
        return None, _S.BadMethodInvalid

    def _bound(self, method_id: ua.NodeId) -> tuple[ua.NodeId | None, int | None]:
        """A method of the object: a standard one nobody here implements may not be called."""
        if method_id in self._handlers:
            return method_id, None
        return None, _S.BadUserAccessDenied


def _too_much(args: list[ua.Variant]) -> int | None:
    if len(args) > MAX_ARGUMENTS:
        return TOO_MANY
    for arg in args:
        value = arg.Value if isinstance(arg, ua.Variant) else arg
        if isinstance(value, str | bytes) and len(value) > MAX_ARGUMENT_BYTES:
            return TOO_LONG
    return None


def refused(status: int, arguments: int) -> ua.CallMethodResult:
    """A call refused before its method ran."""
    result = ua.CallMethodResult(StatusCode=ua.StatusCode(status))
    result.InputArgumentResults = [ua.StatusCode() for _ in range(arguments)]
    if status == _S.BadOutOfRange:
        result.InputArgumentResults = [ua.StatusCode(status) for _ in range(arguments)]
    return result


async def _node_class(node: Node) -> ua.NodeClass | None:
    try:
        return await node.read_node_class()
    except ua.UaStatusCodeError:
        return None


async def _components(node: Node) -> dict[ua.NodeId, str]:
    """The node's components (methods among them), by node id, with their browse names."""
    refs = await node.get_references(
        _HAS_COMPONENT, ua.BrowseDirection.Forward, includesubtypes=True
    )
    return {ref.NodeId: ref.BrowseName.Name for ref in refs}


async def _types_of(obj: Node, obj_class: ua.NodeClass) -> list[Node]:
    """The object's type definition and its supertypes (an object type: its supertypes)."""
    first: Any = obj if obj_class is ua.NodeClass.ObjectType else await obj.read_type_definition()
    if first is None:
        return []
    node = first if isinstance(first, Node) else Node(obj.session, first)
    found: list[Node] = [] if obj_class is ua.NodeClass.ObjectType else [node]
    while True:
        parents = await node.get_references(
            ua.ObjectIds.HasSubtype, ua.BrowseDirection.Inverse, includesubtypes=True
        )
        if not parents:
            return found
        node = Node(obj.session, parents[0].NodeId)
        found.append(node)
