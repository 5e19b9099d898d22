"""`Hub`: every browser gets every event; a browser that stops reading is cut off alone."""

from __future__ import annotations

import asyncio

from ride_machine.rider.ui.hub import Hub
from ride_machine.rider.ui.view import Push


def drain(q: asyncio.Queue[Push | None]) -> list[Push | None]:
    out: list[Push | None] = []
    while not q.empty():
        out.append(q.get_nowait())
    return out


def test_a_stalled_browser_is_cut_off_and_the_others_keep_everything() -> None:
    async def scenario() -> None:
        hub = Hub(capacity=8)
        stalled = hub.subscribe()
        reader = hub.subscribe()
        got: list[Push | None] = []
        for i in range(20):
            hub.publish(Push("sample", i))
            got += drain(reader)  # this one keeps up
        assert [e.data for e in got if e is not None] == list(range(20))
        assert drain(stalled) == [None]  # its stream ends; the page reconnects with a snapshot
        assert len(hub) == 1
        assert hub.dropped == 1

    asyncio.run(scenario())


def test_close_ends_every_stream_and_later_ones_at_once() -> None:
    async def scenario() -> None:
        hub = Hub()
        a, b = hub.subscribe(), hub.subscribe()
        hub.publish(Push("tick", 1))
        hub.close()
        assert [e.kind if e else None for e in drain(a)] == [None]
        assert drain(b) == [None]
        assert drain(hub.subscribe()) == [None]
        hub.publish(Push("tick", 2))  # nobody left: nothing to do, nothing raised
        assert len(hub) == 0

    asyncio.run(scenario())


def test_unsubscribed_browsers_get_nothing_more() -> None:
    async def scenario() -> None:
        hub = Hub()
        q = hub.subscribe()
        hub.unsubscribe(q)
        hub.publish(Push("tick", 1))
        assert q.empty()

    asyncio.run(scenario())
