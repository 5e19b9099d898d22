"""A Rider's confirmation queryable (`rider/<login>/<zid>/confirm`, rider/confirm.py) is declared
with its first request, not when it opens: a Rider that only reads is never asked, and each
remote queryable on a key of its own left the machine's Zenoh ~0.4 KiB the poorer for good
after the Rider closed (bench.rss_soak: 0.42 KiB per connect under read-only Rider churn, the
daemon's RSS growing 5.9 MiB/h). Against the scripted machine (tests/rider/conftest.py)."""

from __future__ import annotations

import time
from pathlib import Path

import zenoh

from ride_machine.schema.commands import Command
from ride_machine.schema.rider import CONFIRMED, DENIED, alive_key, confirm_key, digest
from tests.rider.scripted import Scripted, rider_for

SEEN_WITHIN_S = 5.0
ASK_S = 0.5


def answers(session: zenoh.Session, rider: str, payload: bytes) -> list[bytes]:
    """What the Rider's queryable says about `payload` (nothing: no queryable there)."""
    replies = session.get(confirm_key(rider), payload=digest(payload), timeout=ASK_S)
    return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]


def wait_for_token(session: zenoh.Session, rider: str) -> None:
    """Until the machine's session sees the Rider's liveliness token (bounded): what the Rider
    declared before it has reached the machine by then (one link, in order)."""
    deadline = time.monotonic() + SEEN_WITHIN_S
    while not [r for r in session.liveliness().get(alive_key(rider), timeout=ASK_S) if r.ok]:
        assert time.monotonic() < deadline, f"the token of {rider} never reached the machine"


def test_a_rider_that_has_sent_nothing_declares_no_confirmation_queryable(
    scripted: Scripted, tmp_path: Path
) -> None:
    session = scripted.session
    assert session is not None
    with rider_for(scripted, tmp_path, timeout=2.0) as r:
        wait_for_token(session, r.rider_id)
        assert answers(session, r.rider_id, b"anything") == []


def test_its_first_request_declares_it_and_it_confirms_what_was_sent(
    scripted: Scripted, tmp_path: Path
) -> None:
    session = scripted.session
    assert session is not None
    with rider_for(scripted, tmp_path, timeout=2.0) as r:
        r.command(Command.CHECK_HOME)
        sent = scripted.payloads[-1]
        assert answers(session, r.rider_id, sent) == [CONFIRMED]
        assert answers(session, r.rider_id, b"not sent") == [DENIED]
        r.command(Command.CHECK_HOME)  # declared once: a second request changes nothing
        assert answers(session, r.rider_id, scripted.payloads[-1]) == [CONFIRMED]
    assert answers(session, r.rider_id, sent) == []  # gone with the Rider
