"""A command's facts (`CommandFacts`): the plain values its event and its log line are made of,
with no pydantic at import, so that the history's own process (service/adapters/history_writer.py)
makes both without loading the wire models (bench.rss_soak: 16 MiB of its 33)."""

from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    from ride_machine.schema.commands import Command, CommandRequest, Reply
    from ride_machine.schema.events import CommandEvent
    from ride_machine.service.core.commands.identity import Identity

COMMAND_LOG = logging.getLogger("machine")
"""The logger of a command's one line (`event=command …`), the daemon's own."""

wire_json = json.JSONEncoder(ensure_ascii=False, separators=(",", ":")).encode
"""Plain data as JSON text, as pydantic's serializer writes a model (compact, UTF-8 kept, the
same escapes): for the events the history process makes without the models."""


class CommandFacts(NamedTuple):
    """What a command's event and its log line are made of: plain values taken when it was
    answered. Calling it makes the event (a `Lazy` row); made later, on the event log's writer
    thread or in the history's own process (service/adapters/history.py), sent as the tuple
    it is and made again there with `CommandFacts(*values)`. A tuple: made on the command's
    own thread, where a frozen dataclass took 1 µs and this 0.3."""

    command: str
    transaction_id: str
    rider: str | None
    accepted: bool
    code: str
    message: str
    state: str | None
    repeat: bool
    timecode: float | None
    identity: str | None = None
    """The Rider that confirmed it sent the command (service/bus/confirm.py); `rider` is
    only its claim."""
    operator: str | None = None
    """The person that Rider acted for, as its confirmation named them."""

    @classmethod
    def of(
        cls,
        command: Command,
        request: CommandRequest,
        reply: Reply,
        sender: str | None,
        repeat: bool,
        identity: Identity | None = None,
    ) -> CommandFacts:
        error = reply.error
        return cls(
            command._value_,
            request.transaction_id,
            request.rider or sender,
            reply.success,
            error.code._value_ if error is not None else reply.code._value_,
            error.message if error is not None else "",
            reply.state._value_ if reply.state is not None else None,
            repeat,
            request.timecode,
            identity.rider if identity else None,
            identity.operator if identity else None,
        )

    def __call__(self) -> CommandEvent:
        # Imported on use: only the daemon calls this, the history process writes `details`.
        from ride_machine.schema.events import CommandEvent
        from ride_machine.schema.status import MachineState

        return CommandEvent(
            command=self.command,
            transaction_id=self.transaction_id,
            rider=self.rider,
            identity=self.identity,
            operator=self.operator,
            accepted=self.accepted,
            code=self.code,
            message=self.message,
            state=MachineState(self.state) if self.state is not None else None,
            repeat=self.repeat,
        )

    def details(self) -> str:
        """The event's details as JSON, the text `dump_json(self())` writes (its fields in the
        model's order; tests/service/core/history/test_facts.py holds the two to each other)."""
        return wire_json(
            {
                "kind": "command",
                "command": self.command,
                "transaction_id": self.transaction_id,
                "rider": self.rider,
                "identity": self.identity,
                "operator": self.operator,
                "accepted": self.accepted,
                "code": self.code,
                "message": self.message,
                "state": self.state,
                "repeat": self.repeat,
            }
        )

    def _operator(self) -> str:
        return f" operator={self.operator!r}" if self.operator else ""

    def log_line(self) -> str:
        """The command's log line (its message: `logfmt` adds the time, level and logger)."""
        return (
            f"event=command tx={self.transaction_id} command={self.command}"
            f" rider={self.rider} confirmed={self.identity is not None}{self._operator()}"
            f" timecode={self.timecode} code={self.code} state={self.state}"
        )
