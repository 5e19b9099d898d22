"""The site's event history through the router: `rider --machine '*' events` reads every
machine's log over Zenoh (no file access), and so does a raw wildcard query."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from ride_machine.schema.events import EventPage
from tests.site.stand import Site, run_cli

pytestmark = pytest.mark.integration


def daemon_start_pages(abc: Site, timeout: float = 30.0) -> list[EventPage]:
    """Each machine's page of `daemon_start` events, through the router, once every machine's
    history has written its start (the history process writes a moment after the daemon is
    up; a test that runs first, as in random order, can ask before that)."""
    conf = zenoh.Config.from_file(str(abc.client_config))
    conf.insert_json5("connect/endpoints", json.dumps([abc.router.endpoint]))
    deadline = time.monotonic() + timeout
    with zenoh.open(conf) as session:
        while True:
            query = "machine/*/events?kind=daemon_start;format=json"
            replies = list(session.get(query, timeout=5.0))
            pages = [
                EventPage.model_validate_json(r.ok.payload.to_bytes()) for r in replies if r.ok
            ]
            if (len(pages) == 3 and all(p.events for p in pages)) or time.monotonic() > deadline:
                return pages
            time.sleep(0.1)


def test_rider_reads_every_machines_events_through_the_router(abc: Site) -> None:
    daemon_start_pages(abc)  # every start written
    done = run_cli(abc.rider_cmd("--machine", "*", "events", "--json", "--kind", "daemon_start"))
    assert done.returncode == 0, done.stderr
    events = [json.loads(line) for line in done.stdout.splitlines()]
    assert sorted(e["machine_id"] for e in events) == ["a", "b", "c"]
    assert [e["time"] for e in events] == sorted(e["time"] for e in events)  # merged by time

    summary = ("events", "--summary", "--since", "1h")
    done = run_cli(abc.rider_cmd("--machine", "*", "--json", *summary))
    assert done.returncode == 0, done.stderr
    summaries = json.loads(done.stdout)
    assert [s["machine_id"] for s in summaries] == ["a", "b", "c"]
    assert all(s["daemon_starts"] == 1 for s in summaries)


def test_a_raw_wildcard_query_gets_one_page_per_machine(abc: Site) -> None:
    pages = daemon_start_pages(abc)
    assert sorted(p.machine_id for p in pages) == ["a", "b", "c"]
    assert all([e.kind for e in p.events] == ["daemon_start"] for p in pages)
