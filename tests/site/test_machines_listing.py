"""`rider machines` settles like the default pick before it lists (issue 43, reproduction 5).

Two daemons, `fb` started with `--connect` to `fa`: `rider --connect <fa> machines` listed only
`fa`, 2, 4 and 8 s after the start, while `rider --connect <fa> status` rightly refused
"several machines are alive (fa, fb)". The listing now waits for discovery as the pick does.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from ride_machine.rider.client import Rider
from tests.site.stand import PEER_CONFIG, linked_peers, run_cli

pytestmark = pytest.mark.integration

TRIES = 6


def test_the_listing_names_every_machine_alive_the_pick_knows_of(tmp_path: Path) -> None:
    with linked_peers(tmp_path) as (fa, _):
        cli = [sys.executable, "-m", "ride_machine.rider.cli", "--connect", fa.endpoint]
        cli += ["--zenoh-config", str(PEER_CONFIG), "--json", "machines"]
        listed = []
        for _ in range(TRIES):
            done = run_cli(cli)
            assert done.returncode == 0, done.stderr
            listed.append(sorted(m["id"] for m in json.loads(done.stdout)))
        assert listed == [["fa", "fb"]] * TRIES, listed
        library = []
        for _ in range(TRIES // 2):
            with Rider(None, connect=[fa.endpoint], zenoh_config_path=PEER_CONFIG) as r:
                found = r.machines()
                library.append((sorted(m.id for m in found), found.complete))
    assert library == [(["fa", "fb"], True)] * (TRIES // 2), library
