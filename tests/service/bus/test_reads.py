"""`config/validate` through a real Zenoh session: every candidate, however built, gets exactly one
reply, and that reply stays small."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest
import zenoh

from ride_machine.schema.codec import MAX_PAYLOAD_BYTES, Format, decode
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.findings import Findings
from ride_machine.service.bus.reads import Reads
from ride_machine.service.bus.routes import declare
from ride_machine.service.config.load import MAX_FINDINGS, check_candidate, load_data
from ride_machine.service.config.model import MachineConfig
from tests.service.bus.test_bus_routes import Host

BASE = "machine/v1"
KEY = f"{BASE}/config/validate"


def _no_diag() -> CycleDiag:
    raise AssertionError("not asked")


@pytest.fixture
def validate(session: zenoh.Session) -> Iterator[None]:
    running = MachineConfig()
    reads = Reads(
        BASE,
        None,  # type: ignore[arg-type]  # the config check never reaches the loop
        _no_diag,
        check_config=lambda candidate: check_candidate(running, candidate),
    )
    routes = [r for r in reads.routes() if r.key == "config/validate"]
    declared = declare(session, BASE, Host(), routes)
    yield
    for entity in declared:
        entity.undeclare()


def findings(session: zenoh.Session, candidate: bytes) -> tuple[Findings, int]:
    """The one reply to `candidate`, and its size in bytes."""
    replies = list(session.get(KEY, payload=candidate, timeout=5.0))
    assert len(replies) == 1, replies
    assert replies[0].ok is not None
    data = replies[0].ok.payload.to_bytes()
    return decode(Findings, data, Format.JSON), len(data)


@pytest.mark.parametrize("depth", [600, 990])
@pytest.mark.hazard("H30")
def test_a_candidate_nested_hundreds_deep_gets_one_reply_with_one_finding(
    session: zenoh.Session, validate: None, depth: int
) -> None:
    """About a kilobyte of JSON; its copy ran out of stack and the query went unanswered."""
    candidate = b'{"loop": ' + b"[" * depth + b"]" * depth + b"}"
    report, _ = findings(session, candidate)
    assert not report.ok
    [finding] = report.findings
    assert finding.category == "syntax" and finding.severity == "error"


def test_a_candidate_with_thousands_of_findings_gets_the_first_hundred_and_a_count(
    session: zenoh.Session, validate: None
) -> None:
    """A 64 KiB candidate of unknown keys made 6611 findings, a reply of 1.1 MB."""
    keys: dict[str, int] = {}
    while len(json.dumps({"loop": keys})) < MAX_PAYLOAD_BYTES - 20:
        keys[f"k{len(keys)}"] = 1
    report, size = findings(session, json.dumps({"loop": keys}).encode())
    found = len(load_data({"loop": keys})[1].findings)
    assert found >= len(keys)  # one for each unknown key at least
    assert not report.ok and len(report.findings) == MAX_FINDINGS + 1
    more = report.findings[-1]
    assert more.category == "more" and more.severity == "error"
    assert more.extra["more"] == found - MAX_FINDINGS
    assert size < 64 * 1024
