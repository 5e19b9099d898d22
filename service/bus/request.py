"""One query as the bus sees it: key, format, payload, and the one way to answer or refuse it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import zenoh
from pydantic import BaseModel

from ride_machine.schema.codec import (
    MAX_PAYLOAD_BYTES,
    DecodeError,
    Format,
    decode_raw,
    encode,
    sniff_format,
    too_large,
    validate,
)
from ride_machine.schema.commands import Reply, transaction_id_of
from ride_machine.schema.rider import is_rider_id
from ride_machine.schema.status import MachineState
from ride_machine.service.errors import MachineError, Rejected

M = TypeVar("M", bound=BaseModel)

ENCODINGS = {fmt: zenoh.Encoding(fmt.value) for fmt in Format}
"""Prebuilt, so a reply does not parse its encoding string."""

_UNREAD: Any = object()


class Host(Protocol):
    """Who answers (the daemon's bus or the supervisor's): the time and state a refusal states."""

    def wall(self) -> float: ...

    def state(self) -> MachineState | None: ...


def encoding_of(query: zenoh.Query) -> str | None:
    """The query's encoding as text (read once per query: each read crosses into Zenoh)."""
    encoding = query.encoding
    return str(encoding) if encoding is not None else None


def reply_format(parameters: str, encoding: str | None, sent: Format | None = None) -> Format:
    """JSON when asked (`?format=json` in the selector's `parameters`, a JSON encoding, or JSON
    text sent: `sent`, the payload's `sniff_format`); msgpack otherwise."""
    fmt = zenoh.Parameters(parameters).get("format") if parameters else None
    if fmt is not None:
        return Format.JSON if fmt.lower() == "json" else Format.MSGPACK
    if sent is not None:
        return sent
    return Format.JSON if encoding and encoding.startswith(Format.JSON) else Format.MSGPACK


def send(
    query: zenoh.Query,
    key: str | zenoh.KeyExpr,
    model: BaseModel,
    fmt: Format,
    packed: bytes | None = None,
) -> None:
    """The one reply of a query, and its end (the caller's `get` returns without a timeout).
    `packed`: the model's msgpack bytes, made already (a command's, `TransactionLog.wire`).

    Every reply of the bus goes out here (or through `put`, for a query with several)."""
    data = packed if packed is not None and fmt is Format.MSGPACK else encode(model, fmt)
    with query:
        query.reply(key, data, encoding=ENCODINGS[fmt])


def put(query: zenoh.Query, key: str | zenoh.KeyExpr, model: BaseModel, fmt: Format) -> None:
    """One of several replies to a query; the caller ends the query (`with query:`)."""
    query.reply(key, encode(model, fmt), encoding=ENCODINGS[fmt])


@dataclass(slots=True, eq=False)
class Request:
    """A query with its key, payload and reply format; answered once by `reply` or `refuse`."""

    query: zenoh.Query
    key: str
    body: bytes
    """The payload as sent; empty when it is larger than any request may be (`size`): such a
    payload is never copied out of Zenoh, and `payload` refuses it."""
    encoding: str | None
    """The query's encoding, as text (`encoding_of`)."""
    fmt: Format
    host: Host
    command: str | None = None
    """The command a refusal names (set once the key is known to be one)."""
    transaction_id: str | None = None
    """The id a refusal echoes; without one, whatever id the payload carries."""
    sent: Format | None = None
    """The payload's own format (`sniff_format`), once it has been told; None: not yet."""
    size: int = 0
    """The payload's length in bytes, as sent."""
    _raw: Any = _UNREAD

    @property
    def payload(self) -> bytes:
        """The payload; `Rejected` (PAYLOAD_TOO_LARGE) past `MAX_PAYLOAD_BYTES`: a handler that
        reads it refuses such a request, one that never does (a read) answers as usual."""
        if self.size > MAX_PAYLOAD_BYTES:
            raise Rejected(too_large(self.size))
        return self.body

    @property
    def wild(self) -> bool:
        """The key has a wildcard: it may reach many keys (and many machines)."""
        key = self.key
        return "*" in key or "$" in key

    def raw(self) -> Any:
        """The payload as plain data (None when empty); `Rejected` when it cannot be read."""
        if self._raw is _UNREAD:
            data = self.payload
            self._raw = None
            if data:
                try:
                    sent = self.sent or sniff_format(data, self.encoding)
                    self._raw = decode_raw(data, sent)
                except DecodeError as exc:
                    raise Rejected(exc.error) from None
        return self._raw

    def decode(self, model: type[M]) -> M:
        """The payload as `model`; `Rejected` names the first bad field."""
        try:
            value = validate(model, self.raw())
        except DecodeError as exc:
            raise Rejected(exc.error) from None
        self.transaction_id = getattr(value, "transaction_id", None)
        return value

    def reply(
        self,
        model: BaseModel,
        key: str | zenoh.KeyExpr | None = None,
        packed: bytes | None = None,
    ) -> None:
        send(self.query, self.key if key is None else key, model, self.fmt, packed)

    def refuse(self, error: MachineError) -> None:
        """The one wire shape of a refusal: a `Reply` with `success: false` and the error."""
        tid = self.transaction_id
        if tid is None:
            try:
                tid = transaction_id_of(self.raw())
            except Rejected:
                tid = None
        reply = Reply.failure(
            error.to_error(),
            transaction_id=tid,
            command=self.command,
            timecode=self.host.wall(),
            state=self.host.state(),
        )
        if not error.error_reply:
            send(self.query, self.key, reply, self.fmt)
            return
        with self.query as query:
            query.reply_err(encode(reply, self.fmt), encoding=ENCODINGS[self.fmt])

    def answer(self, fn: Callable[[], BaseModel]) -> None:
        """Reply with what `fn` makes, or refuse with the `MachineError` it raises (for work
        that runs away from the dispatcher: the scan thread, a reader thread)."""
        try:
            model = fn()
        except MachineError as exc:
            self.refuse(exc)
            return
        self.reply(model)


ATTACHMENT_MAX_BYTES = 128
"""`rider=` and the longest Rider id (a 64-character login, `/`, a 32-digit session id) fit."""


def sender_of(query: zenoh.Query) -> str | None:
    """The Rider id from the query's attachment (`rider=<login>/<zid>`; a schema-1 Rider's
    `rider=<zid>`), if it sent one. Said by the sender: the login part is its own claim,
    which the ACL profiles do not check on a query (docs/security.md)."""
    attachment = query.attachment  # one read: each crosses into Zenoh
    # Its length first (no copy): no Rider id makes an attachment longer than this.
    if attachment is None or len(attachment) > ATTACHMENT_MAX_BYTES:
        return None
    text = attachment.to_bytes().decode(errors="replace")
    name, _, value = text.partition("=")
    if name != "rider":
        return None
    return value if is_rider_id(value) or (value.isalnum() and len(value) <= 32) else None
