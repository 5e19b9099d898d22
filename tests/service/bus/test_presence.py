"""Riders' presence and other holders of this machine's id, as the bus hands them to the loop:
a change the loop's inbox has no room for is counted and said, not lost in silence."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from types import SimpleNamespace

import pytest
import zenoh

from ride_machine.service.bus.presence import Presence
from ride_machine.service.config.model import MachineConfig


@dataclass
class FullInbox:
    """The loop's port with its inbox full: every task is refused."""

    refused: list[object] = field(default_factory=list)

    def submit(self, task: object) -> bool:
        self.refused.append(task)
        return False

    def rider_back(self, rider: str) -> None:
        pass

    def rider_gone(self, rider: str) -> None:
        pass


def _sample(key: str, kind: zenoh.SampleKind = zenoh.SampleKind.PUT) -> zenoh.Sample:
    return SimpleNamespace(key_expr=key, kind=kind)  # type: ignore[return-value]


def test_a_presence_change_the_inbox_cannot_take_is_counted_and_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    port = FullInbox()
    session = SimpleNamespace(zid=lambda: "self")
    presence = Presence(session, port, MachineConfig())  # type: ignore[arg-type]
    with caplog.at_level(logging.WARNING):
        for i in range(4):
            presence._on_rider(_sample(f"rider/bay1/{i:x}/alive"))
        presence._on_holder(_sample("machine/m1/holder/other"))
    assert len(port.refused) == presence.dropped == 5
    lines = [r.getMessage() for r in caplog.records if "event=presence_dropped" in r.getMessage()]
    assert lines == [  # the first, then at each power of two
        "event=presence_dropped cause=inbox_full task=rider rider=bay1/0 alive=True dropped=1",
        "event=presence_dropped cause=inbox_full task=rider rider=bay1/1 alive=True dropped=2",
        "event=presence_dropped cause=inbox_full task=rider rider=bay1/3 alive=True dropped=4",
    ]
