"""`Hub`: fans events out to every connected browser without ever waiting for one."""

from __future__ import annotations

import asyncio
import contextlib
import logging

from .view import Push

log = logging.getLogger("rider.ui")

QUEUE_CAPACITY = 512


class Hub:
    """One bounded queue per browser; a browser that falls behind is cut off (it reconnects
    and starts again from a snapshot), so a slow page can never hold up the others."""

    def __init__(self, capacity: int = QUEUE_CAPACITY) -> None:
        self.capacity = capacity
        self._subs: set[asyncio.Queue[Push | None]] = set()
        self.closed = False
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._subs)

    def subscribe(self) -> asyncio.Queue[Push | None]:
        """A queue of events; `None` means the stream is over."""
        q: asyncio.Queue[Push | None] = asyncio.Queue(self.capacity + 1)
        if self.closed:
            q.put_nowait(None)
        else:
            self._subs.add(q)
        return q

    def unsubscribe(self, q: asyncio.Queue[Push | None]) -> None:
        self._subs.discard(q)

    def publish(self, event: Push) -> None:
        for q in list(self._subs):
            if q.qsize() >= self.capacity:
                self._end(q)
                self.dropped += 1
                log.warning(
                    "event=ui_stream_cut reason=behind queued=%d cut=%d: the page reconnects"
                    " from a snapshot",
                    self.capacity,
                    self.dropped,
                )
            else:
                q.put_nowait(event)

    def close(self) -> None:
        """End every stream (server shutdown); later subscribers end at once."""
        self.closed = True
        for q in list(self._subs):
            self._end(q)

    def _end(self, q: asyncio.Queue[Push | None]) -> None:
        self._subs.discard(q)
        while not q.empty():
            with contextlib.suppress(asyncio.QueueEmpty):
                q.get_nowait()
        q.put_nowait(None)
