"""The pipe between the daemon and its history process: the messages each way, a batch's items,
and how a message is written and read whole."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import msgpack

from ride_machine.schema.codec import dump_json
from ride_machine.service.core.history.held import CommandFacts, Held, LogLine

from .eventdb import Row

# daemon → history process (`[FLUSH, token, timeout_s]`: the daemon waits no longer for the
# answer, so the process answers by then, written or not, and reads the pipe again)
BATCH, FLUSH, FAILED = 0, 1, 2
# history process → daemon
WROTE, FLUSHED, LOG = 0, 1, 2
# an item of a batch
MADE, COMMAND, LINE = 0, 1, 2

READ_BYTES = 1 << 16

Item = tuple[Any, ...]
"""`(MADE, kind, details JSON, wall, cycle)`, `(COMMAND, wall, cycle, facts, logged)`, or
`(LINE, text)`: a command's log line whose events the daemon made (`EventLog.defer`)."""


def rows_in(entry: Row | Held | str) -> int:
    if isinstance(entry, str):
        return 0  # a log line, no event
    return len(entry.rows) if isinstance(entry, Held) else 1


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


def encode(message: list[Any]) -> bytes:
    data: bytes = msgpack.packb(message, use_bin_type=True)
    return data


def write_all(out: Any, data: bytes) -> None:
    """All of `data` to an unbuffered pipe, however many writes it takes."""
    view = memoryview(data)
    while view:
        n = out.write(view)
        view = view[n or 0 :]


def messages(fd: int) -> Iterator[tuple[Any, ...]]:
    """Each message read from `fd`, until the other end closes it."""
    # Its buffer sized to a read (it grows for a longer message): msgpack's default, 1 MiB,
    # ended up resident on both sides of the pipe as messages went through it.
    unpacker = msgpack.Unpacker(raw=False, use_list=False, read_size=READ_BYTES)
    while data := os.read(fd, READ_BYTES):
        unpacker.feed(data)
        yield from unpacker
