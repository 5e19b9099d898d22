"""What the daemon sends its history process of what it queued (an event, a command's held
record, a log line): plain values, the items of a batch (service/adapters/history_pipe.py).
The daemon's side only: it reads the wire models, which the history process never loads."""

from __future__ import annotations

from ride_machine.schema.codec import dump_json
from ride_machine.service.core.history.facts import CommandFacts
from ride_machine.service.core.history.held import Held, LogLine

from .eventdb import Row
from .history_pipe import COMMAND, LINE, MADE, Item


def batch_items(entry: Row | Held | str) -> list[Item]:
    """What the history process needs of a queued event, a command's held record or a log
    line: plain values. A held record's own events are made here only when they are not a
    command's."""
    if isinstance(entry, str):
        return [(LINE, entry)]  # written by the process in its place, as its own lines are
    if not isinstance(entry, Held):
        kind, text, wall, cycle = entry
        return [(MADE, kind, text, wall, cycle)]
    then = entry.then
    logged = then.facts if isinstance(then, LogLine) else None
    out: list[Item] = []
    for row in entry.rows:
        if isinstance(row, CommandFacts):
            out.append((COMMAND, entry.wall, entry.cycle, row, row is logged))
            if row is logged:
                then = None
        else:
            details = row() if callable(row) else row
            out.append((MADE, details.kind, dump_json(details), entry.wall, entry.cycle))
    if then is not None:  # a line that is not its command's own: written here
        then()
    return out
