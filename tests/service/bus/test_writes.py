"""Parameter writes through a real Zenoh session: a refused try at a safety setting gets its one
reply and is on the record, in a form every reader of the history can carry."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh
from pydantic import BaseModel

from ride_machine.schema.codec import Format, encode
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import ParamEvent
from ride_machine.service.bus.routes import declare
from ride_machine.service.bus.writes import Writes
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.storage.params import ParamRegistry
from ride_machine.service.core.storage.persist import ParamStore
from tests.service.bus.test_bus_routes import WALL, Host, ask

BASE = "machine/w1"


class StandingStill:
    """The loop as a parameter write sees it: nothing moving, no records held."""

    def moving(self) -> bool:
        return False

    def release_records(self, timeout: float) -> None:
        pass


@dataclass
class Recorded:
    """The event history as the write route uses it."""

    events: list[BaseModel] = field(default_factory=list)

    def emit_now(self, details: BaseModel, cycle: int | None = None) -> None:
        self.events.append(details)


def _no_diag() -> CycleDiag:
    raise AssertionError("not asked")


@pytest.fixture
def history(session: zenoh.Session, tmp_path: Path) -> Iterator[Recorded]:
    recorded = Recorded()
    writes = Writes(
        BASE,
        StandingStill(),  # type: ignore[arg-type]
        CycleStats(0.01),
        _no_diag,
        lambda: WALL,
        params=ParamRegistry(MachineConfig(), ParamStore(tmp_path)),
        events=recorded,  # type: ignore[arg-type]
    )
    routes = [r for r in writes.routes() if r.key == "params/**"]
    declared = declare(session, BASE, Host(), routes)
    yield recorded
    for entity in declared:
        entity.undeclare()


@pytest.mark.hazard("H30")
def test_a_safety_setting_written_as_a_310_digit_integer_is_refused_and_recorded(
    session: zenoh.Session, history: Recorded
) -> None:
    """No float holds it: the write raised OverflowError, got no reply and left no record."""
    payload = b'{"transaction_id": "t-big", "value": 1' + b"0" * 310 + b"}"
    (answer,) = ask(session, f"{BASE}/params/rider_loss.timeout_s", payload)
    reply = answer.reply()
    assert reply.error is not None and reply.error.code is ErrorCode.PARAM_OUT_OF_RANGE
    assert reply.error.path == "/value" and "rider_loss.timeout_s" in reply.error.message
    assert reply.transaction_id == "t-big"
    [event] = history.events
    assert isinstance(event, ParamEvent)
    assert (event.kind, event.accepted, event.old) == ("safety_changed", False, 0.5)
    assert event.new == "an integer of 1030 bits"  # every history read is msgpack: no bigint
    encode(event, Format.MSGPACK)
