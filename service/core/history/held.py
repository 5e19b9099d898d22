"""What the loop holds for the history until its next cycle: a command's facts (`CommandFacts`,
service/core/history/facts.py: plain values made into its event and log line later, on the
event log's writer or in the history's own process), its log line, and the records of a
command (`Held`), bounded per cycle (`hold_limit`). Sent between processes as plain tuples
(service/adapters/history_pipe.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ride_machine.schema.events import KnownDetails
from ride_machine.service.logfmt import info

from .facts import COMMAND_LOG, CommandFacts


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
