"""The `events` queryable under careless or hostile selectors, asked with plain zenoh-python:
every one gets an answer (a page or a BAD_PAYLOAD naming the parameter), JSON when `format=json`
is given with either separator, and the reader keeps answering afterwards."""

from __future__ import annotations

import json
import time
from pathlib import Path

import msgpack
import pytest
import zenoh

from ride_machine.schema.commands import Reply
from ride_machine.schema.events import EventPage
from tests.integration.support import one_reply
from tests.procs import Daemon, running_daemon

pytestmark = pytest.mark.integration


def ask(session: zenoh.Session, selector: str) -> tuple[str, bytes]:
    """The one reply's encoding and payload (retried while the daemon is not yet seen)."""
    sample = one_reply(session, selector)
    return str(sample.encoding), sample.payload.to_bytes()


def first_page(session: zenoh.Session, timeout: float = 10.0) -> EventPage:
    """The history's newest event once it has one: the history process writes the daemon's
    start a moment after the daemon answers (on a loaded host, after the first query)."""
    deadline = time.monotonic() + timeout
    while True:
        _, payload = ask(session, "machine/m1/events?last=1;format=json")
        page = EventPage.model_validate_json(payload)
        if page.events or time.monotonic() > deadline:
            return page
        time.sleep(0.05)


def session_of(daemon: Daemon) -> zenoh.Session:
    conf = zenoh.Config.from_file(str(daemon.zenoh_config))
    conf.insert_json5("connect/endpoints", json.dumps([daemon.endpoint]))
    return zenoh.open(conf)


def test_bad_selectors_are_answered_and_the_reader_lives_on(tmp_path: Path) -> None:
    with running_daemon(tmp_path) as daemon, session_of(daemon) as session:
        assert first_page(session).events[0].kind == "daemon_start"
        for selector, param in [
            ("machine/m1/events?since=99999999999999999999999;format=json", "?since"),
            ("machine/m1/events?kind=unknown;format=json", "?kind"),
            ("machine/m1/events?last=0;format=json", "?last"),
            ("machine/m1/events?format=xml", "?format"),
        ]:
            encoding, payload = ask(session, selector)
            if "xml" in selector:  # a format it does not know: the error in the default msgpack
                reply = Reply.model_validate(msgpack.unpackb(payload))
            else:
                assert encoding.startswith("application/json"), selector
                reply = Reply.model_validate_json(payload)
            assert reply.error is not None and reply.error.code == "BAD_PAYLOAD", selector
            assert reply.error.path == param, selector
        # `&` separates as `;` does, for the format too; and a wildcard key reaches the page.
        for selector in ("machine/m1/events?last=1&format=json", "machine/*/events/**?format=json"):
            encoding, payload = ask(session, selector)
            assert encoding.startswith("application/json"), selector
            page = EventPage.model_validate_json(payload)
            assert page.events[0].kind == "daemon_start", selector
