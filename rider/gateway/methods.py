"""The machine's commands as OPC UA methods, through the Rider client's command path.

Every call answers with four output arguments — `Code`, `Message`, `TransactionId`, `State` —
and a status: Good when the machine accepted the command, Bad when it refused (the machine's
error code and text in `Code` and `Message`), when the argument is wrong, or when no reply came.
"""

from __future__ import annotations

import json
import logging
import sys
import time
import uuid
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from asyncua import ua
from pydantic import ValidationError

from ride_machine.rider.client import MachineTimeout, NoMachine, RiderError
from ride_machine.schema.codec import json_pointer
from ride_machine.schema.commands import Command, CommandRequest, Reply, Session, StartRequest
from ride_machine.schema.errors import ErrorCode

from .calls import MAX_ARGUMENT_BYTES, Calls, Invocation, Role
from .security import Caller

log = logging.getLogger(__name__)

_S = ua.StatusCodes
REFUSALS: dict[str, int] = {
    ErrorCode.WRONG_STATE: _S.BadInvalidState,
    ErrorCode.ESTOP_ACTIVE: _S.BadInvalidState,
    ErrorCode.NOT_CALIBRATED: _S.BadInvalidState,
    ErrorCode.NOT_HOME: _S.BadInvalidState,
    ErrorCode.DUPLICATE_ID: _S.BadInvalidState,
    ErrorCode.BAD_PAYLOAD: _S.BadInvalidArgument,
    ErrorCode.INVALID_SESSION: _S.BadInvalidArgument,
    ErrorCode.BUSY: _S.BadTooManyOperations,
    ErrorCode.STALE_REQUEST: _S.BadTimeout,
}
"""The machine's refusal codes as OPC UA status codes; any other is BadUnexpectedError."""


class CallRefused(Exception):
    """A call refused before it reached the machine: an OPC UA status and the text."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code


Send = Callable[[str, Command, CommandRequest], Awaitable[Reply]]
"""Sends a command to a machine (by id) on a worker thread; the machine's reply."""
RiderFor = Callable[[Caller], Awaitable[str]]
"""The Rider id the caller's session commands under (its supervision declared)."""


@dataclass
class Commander:
    """Turns method calls into commands: who may call, the request, the reply as a result."""

    send: Send
    rider_for: RiderFor
    read_only: bool

    async def call(
        self, caller: Caller, machine_id: str, command: Command, args: list[ua.Variant]
    ) -> ua.CallMethodResult:
        """One method call, answered as the machine answered (never a silent success)."""
        tid = uuid.uuid4().hex[:16]
        try:
            session = _session_arg(args) if command is Command.START else _no_args(command, args)
            rider = await self.rider_for(self._may(caller))
            request = _request(command, session, tid, rider)
            reply = await self.send(machine_id, command, request)
        except CallRefused as exc:
            log.info(
                "event=opcua_call_refused machine=%s command=%s code=%s",
                machine_id,
                command,
                exc.code,
            )
            return _result(exc.status, exc.code, str(exc), tid, "")
        except NoMachine as exc:
            return _result(_S.BadNoCommunication, "NO_MACHINE", str(exc), tid, "")
        except MachineTimeout as exc:
            return _result(_S.BadTimeout, "NO_REPLY", str(exc), tid, "")
        except RiderError as exc:
            return _result(_S.BadCommunicationError, "BUS_ERROR", str(exc), tid, "")
        state = str(reply.state or "")
        log.info(
            "event=opcua_call machine=%s command=%s tx=%s code=%s",
            machine_id,
            command,
            tid,
            reply.error.code if reply.error else reply.code,
        )
        if reply.success:
            return _result(_S.Good, str(reply.code), "", tid, state)
        error = reply.error
        code = str(error.code) if error else str(reply.code)
        text = error.message if error else reply.error_message
        where = f" at {error.path}" if error and error.path else ""
        return _result(REFUSALS.get(code, _S.BadUnexpectedError), code, text + where, tid, state)

    def _may(self, caller: Caller) -> Caller:
        if not caller.operator:  # the Call service refuses it first; kept as a guard
            raise CallRefused(_S.BadUserAccessDenied, "ACCESS_DENIED", "needs the operator role")
        if self.read_only:
            raise CallRefused(
                _S.BadUserAccessDenied, "READ_ONLY", "this gateway is read-only (--monitor)"
            )
        return caller


def _no_args(command: Command, args: list[ua.Variant]) -> Session | None:
    """The commands but Start take no argument (so no session)."""
    if args:
        raise CallRefused(_S.BadTooManyArguments, "BAD_PAYLOAD", f"{command} takes no argument")
    return None


def _request(command: Command, session: Session | None, tid: str, rider: str) -> CommandRequest:
    """The request the Rider client sends, naming the caller's Rider (the deadman's)."""
    now = time.time()
    if command is Command.START:
        return StartRequest(transaction_id=tid, timecode=now, rider=rider, session=session)
    return CommandRequest(transaction_id=tid, timecode=now, rider=rider)


def _session_arg(args: list[ua.Variant]) -> Session | None:
    """Start's one argument: a session as JSON text; empty for the default session."""
    if len(args) > 1:
        raise CallRefused(_S.BadTooManyArguments, "BAD_PAYLOAD", "Start takes one argument")
    text = args[0] if args else ""
    if isinstance(text, ua.Variant):
        text = text.Value
    if text is None or text == "":
        return None
    if not isinstance(text, str):
        raise CallRefused(
            _S.BadTypeMismatch,
            "BAD_PAYLOAD",
            f"Session must be a String, not {type(text).__name__}",
        )
    if len(text.encode()) > MAX_ARGUMENT_BYTES:  # characters passed the Call service's bound
        raise CallRefused(
            _S.BadOutOfRange, "BAD_PAYLOAD", f"Session is longer than {MAX_ARGUMENT_BYTES} bytes"
        )
    too_long: list[_TooLong] = []
    try:
        data = json.loads(text, parse_int=lambda digits: _int(digits, too_long))
    except json.JSONDecodeError as exc:
        raise CallRefused(
            _S.BadInvalidArgument, "BAD_PAYLOAD", f"Session is not JSON: {exc.msg} at {exc.pos}"
        ) from exc
    except RecursionError as exc:
        raise CallRefused(
            _S.BadInvalidArgument, "BAD_PAYLOAD", "Session nests deeper than any session does"
        ) from exc
    if too_long:
        path = json_pointer(_path_of(data, too_long[0])) or "/"
        raise CallRefused(
            _S.BadInvalidArgument,
            "BAD_PAYLOAD",
            f"Session {path}: an integer of {len(too_long[0].lstrip('-'))} digits"
            f" (at most {sys.get_int_max_str_digits()})",
        )
    try:
        return Session.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        path = json_pointer(first["loc"]) or "/"
        raise CallRefused(
            _S.BadInvalidArgument, "BAD_PAYLOAD", f"Session {path}: {first['msg']}"
        ) from exc


class _TooLong(str):
    """An integer's text past Python's digit limit (`int` raises ValueError, no JSON error)."""


def _int(digits: str, too_long: list[_TooLong]) -> int | _TooLong:
    """`json`'s integer, or the text kept (and noted) when it is too long to convert."""
    try:
        return int(digits)
    except ValueError:
        too_long.append(_TooLong(digits))
        return too_long[-1]


def _path_of(data: Any, target: object) -> tuple[str | int, ...]:
    """Where `target` (by identity) sits in parsed JSON, as keys and indexes (iterative: the
    JSON may nest as deep as the parser let it)."""
    stack: list[tuple[Any, tuple[str | int, ...]]] = [(data, ())]
    while stack:
        node, path = stack.pop()
        if node is target:
            return path
        if isinstance(node, dict):
            stack.extend((v, (*path, k)) for k, v in node.items())
        elif isinstance(node, list):
            stack.extend((v, (*path, i)) for i, v in enumerate(node))
    return ()


def _result(status: int, code: str, message: str, tid: str, state: str) -> ua.CallMethodResult:
    values = (code, message, tid, state)
    return ua.CallMethodResult(
        StatusCode=ua.StatusCode(status),
        OutputArguments=[ua.Variant(v, ua.VariantType.String) for v in values],
    )


def bind_methods(
    methods: dict[Command, ua.NodeId], machine_id: str, commander: Commander, calls: Calls
) -> None:
    """A machine's methods (its object's, rider/gateway/typemodel.py), each bound to
    `commander` for this machine, for the operator."""
    for command, nid in methods.items():
        calls.bind(nid, Role.OPERATOR, _bind(commander, machine_id, command))


def _bind(
    commander: Commander, machine_id: str, command: Command
) -> Callable[[Invocation], Awaitable[ua.CallMethodResult]]:
    """One machine's command, for the Call service (which checked who calls, and on what)."""

    async def method(call: Invocation) -> ua.CallMethodResult:
        return await commander.call(call.caller, machine_id, command, call.arguments)

    return method
