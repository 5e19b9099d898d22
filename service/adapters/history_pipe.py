"""The pipe between the daemon and its history process: the messages each way, a batch's items,
and how a message is written and read whole (the daemon's end, `Outlet`, never waits without
bound). Both sides import it: msgpack and the standard library only (the history process loads
no pydantic)."""

from __future__ import annotations

import contextlib
import os
import select
import threading
from collections.abc import Callable, Iterator
from enum import Enum
from typing import IO, Any

import msgpack

# daemon → history process (`[FLUSH, token, timeout_s]`: the daemon waits no longer for the
# answer, so the process answers by then, written or not, and reads the pipe again;
# `[BATCH, dropped, items, again]`: the first `again` items were sent to a process that ended
# before it confirmed them, and are written unless that one had stored them already)
BATCH, FLUSH, FAILED = 0, 1, 2
# history process → daemon
WROTE, FLUSHED, LOG = 0, 1, 2
# an item of a batch
MADE, COMMAND, LINE = 0, 1, 2

READ_BYTES = 1 << 16
POLL_S = 0.05
"""How often a sender waiting for room in a full pipe asks whether to give up."""

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


def write_within(fd: int, data: bytes, give_up: Callable[[], bool]) -> bool:
    """All of `data` to a non-blocking pipe, waiting for room while `give_up()` says not to;
    False once it does: part of a long message may be in the pipe then, and its reader must be
    ended. A message of at most `select.PIPE_BUF` bytes goes whole or not at all. OSError
    when the pipe has no reader."""
    view = memoryview(data)
    room = select.poll()
    room.register(fd, select.POLLOUT)
    while True:
        with contextlib.suppress(BlockingIOError):
            view = view[os.write(fd, view) :]
        if not view:
            return True
        if give_up():
            return False
        room.poll(POLL_S * 1000)


class Sent(Enum):
    """How a message to the history process went."""

    TAKEN = "taken"
    GONE = "gone"
    """No reader (the process ended), or the pipe closed: none of it was taken."""
    LATE = "late"
    """Given up in a full pipe; a long message may be half in it: its reader must be ended."""


class Outlet:
    """The daemon's end of a history process's stdin, non-blocking: one message at a time goes
    whole, waiting for room only while its sender does not give up (a process that reads no
    more, stopped or on a hung disk, holds no thread of the daemon for good)."""

    def __init__(self, pipe: IO[bytes]) -> None:
        self._pipe = pipe
        os.set_blocking(pipe.fileno(), False)
        self._lock = threading.Lock()

    def send(self, message: list[Any], give_up: Callable[[], bool]) -> Sent:
        data = encode(message)
        while not self._lock.acquire(timeout=POLL_S):  # another message on its way
            if give_up():
                return Sent.LATE
        try:
            if self._pipe.closed:
                return Sent.GONE
            taken = write_within(self._pipe.fileno(), data, give_up)
        except OSError:
            return Sent.GONE
        finally:
            self._lock.release()
        return Sent.TAKEN if taken else Sent.LATE

    def close(self, timeout: float) -> None:
        """Close it once no message is on its way (waited for at most `timeout`): the process
        reads to its end, writes what it has and exits."""
        if self._lock.acquire(timeout=max(0.0, timeout)):
            try:
                with contextlib.suppress(OSError):
                    self._pipe.close()
            finally:
                self._lock.release()


def messages(fd: int) -> Iterator[tuple[Any, ...]]:
    """Each message read from `fd`, until the other end closes it."""
    # Its buffer sized to a read (it grows for a longer message): msgpack's default, 1 MiB,
    # ended up resident on both sides of the pipe as messages went through it.
    unpacker = msgpack.Unpacker(raw=False, use_list=False, read_size=READ_BYTES)
    while data := os.read(fd, READ_BYTES):
        unpacker.feed(data)
        yield from unpacker
