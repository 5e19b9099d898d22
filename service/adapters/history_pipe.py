"""The pipe between the daemon and its history process: the messages each way, a batch's items,
and how a message is written and read whole. Both sides import it: msgpack and the standard
library only (the history process loads no pydantic)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import msgpack

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
