"""The site's event history through the router: `rider --machine '*' events` reads every
machine's log over Zenoh (no file access), and so does a raw wildcard query."""

from __future__ import annotations

import json

import pytest
import zenoh

from schema.events import EventPage
from tests.site.stand import Site, run_cli

pytestmark = pytest.mark.integration


def test_rider_reads_every_machines_events_through_the_router(abc: Site) -> None:
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
    conf = zenoh.Config.from_file(str(abc.client_config))
    conf.insert_json5("connect/endpoints", json.dumps([abc.router.endpoint]))
    with zenoh.open(conf) as session:
        replies = list(session.get("machine/*/events?kind=daemon_start;format=json", timeout=5.0))
    pages = [EventPage.model_validate_json(r.ok.payload.to_bytes()) for r in replies if r.ok]
    assert sorted(p.machine_id for p in pages) == ["a", "b", "c"]
    assert all([e.kind for e in p.events] == ["daemon_start"] for p in pages)
