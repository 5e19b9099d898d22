"""What the loop holds for the history until its next cycle: a command's facts (`CommandFacts`,
plain values made into its event and log line later, on the event log's writer or in the
history's own process), its log line, and the records of a command (`Held`), bounded per
cycle (`hold_limit`). Sent between processes as plain tuples (service/adapters/history_pipe.py).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.events import CommandEvent, KnownDetails
from ride_machine.schema.status import MachineState
from ride_machine.service.core.commands.identity import Identity
from ride_machine.service.logfmt import info

COMMAND_LOG = logging.getLogger("machine")
"""The logger of a command's one line (`event=command …`), the daemon's own."""


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

    def _operator(self) -> str:
        return f" operator={self.operator!r}" if self.operator else ""

    def log_line(self) -> str:
        """The command's log line (its message: `logfmt` adds the time, level and logger)."""
        return (
            f"event=command tx={self.transaction_id} command={self.command}"
            f" rider={self.rider} confirmed={self.identity is not None}{self._operator()}"
            f" timecode={self.timecode} code={self.code} state={self.state}"
        )


@dataclass(frozen=True, slots=True)
class LogLine:
    """A command's log line as a held record's `then`: written where its events are made."""

    facts: CommandFacts

    def __call__(self) -> None:
        info(COMMAND_LOG, self.facts.log_line())

    @staticmethod
    def write(text: str) -> None:
        """A line made earlier (`facts.log_line()`), written now in its place."""
        info(COMMAND_LOG, text)


Lazy = KnownDetails | CommandFacts | Callable[[], KnownDetails]
"""An event, or what makes it when it is written (a command's own event: off its reply's path)."""
Emit = Callable[[Lazy], None]


@dataclass(slots=True, eq=False)
class Held:
    """A command's events, compared when it ran, and its log line (`then`), made later."""

    rows: list[Lazy]
    wall: float
    cycle: int
    then: Callable[[], None] | None

    def write(self, emit: Callable[[KnownDetails, float, int | None], None]) -> None:
        """Make the events and hand each to `emit`, then write the log line."""
        for row in self.rows:
            emit(row() if callable(row) else row, self.wall, self.cycle)
        if self.then is not None:
            self.then()


HOLD_PER_MS = 1
"""Commands whose events a cycle hands over, per millisecond of its period (10 at 10 ms, 1 at
1 ms): a command beyond that hands over the oldest one held itself, on its own thread, so a
command storm does not lengthen the scan cycle (bench.throughput, section 8). Handing over to the
event log only queues the record (`EventLog.defer`): its writer makes it."""


def hold_limit(period_s: float) -> int:
    return max(1, round(period_s * 1000 * HOLD_PER_MS))
