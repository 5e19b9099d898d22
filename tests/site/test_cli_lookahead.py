"""The `rider` command starts the default-machine lookup as soon as its session is open and loads
the client meanwhile (rider/cli.py, issue 59's start-up): the lookup is the same one, so its
answers are too. Two peer daemons linked to each other are both seen, through the CLI, every
time (issue 22's case); a lookahead that waited less than a command needs is not taken for it,
and one that waited long enough is taken as it is."""

from __future__ import annotations

from pathlib import Path

import pytest

from ride_machine.rider.blocking import Rider
from ride_machine.rider.cli import EXIT_AMBIGUOUS
from ride_machine.rider.discovery import MOTION_SETTLE_S, SETTLE_S, Lookahead
from ride_machine.rider.link import Link
from tests.procs import rider_cmd, run_bounded, start_daemon
from tests.site.stand import PEER_CONFIG, linked_peers

TRIES = 6


def _link(endpoint: str) -> Link:
    """A one-shot CLI's link: a peer on the shipped zenoh.json5, supervising nothing."""
    return Link(
        PEER_CONFIG,
        [endpoint],
        None,
        key_prefix="machine",
        timeout=2.0,
        retries=1,
        supervise=False,
        zenoh_threads=1,
    )


@pytest.mark.integration
def test_the_cli_sees_both_of_two_linked_peer_daemons_every_time(tmp_path: Path) -> None:
    with linked_peers(tmp_path) as (fa, fb):
        results = [
            run_bounded(
                rider_cmd(
                    *["--connect", (fb, fa)[n % 2].endpoint],
                    *["--zenoh-config", str(PEER_CONFIG), "status"],
                ),
                timeout=60,
            )
            for n in range(TRIES)
        ]
    for done in results:
        assert done.returncode == EXIT_AMBIGUOUS, done.stderr
        assert "several machines are alive (fa, fb)" in done.stderr


@pytest.mark.integration
def test_a_lookahead_is_taken_only_when_it_waited_long_enough(tmp_path: Path) -> None:
    daemon = start_daemon(tmp_path, "m1", extra=["--zenoh-config", str(PEER_CONFIG)])
    try:
        short = _link(daemon.endpoint)
        short.open()
        early = Lookahead(SETTLE_S, short.lookup)
        with Rider.on_link(short, None, early) as rider:
            assert rider.pick_machine(motion=True) == "m1"
            assert rider.discovery is not early.result()  # looked up again, for longer
            assert rider.discovery is not None
            assert rider.discovery.waited_s >= MOTION_SETTLE_S
        long = _link(daemon.endpoint)
        long.open()
        early = Lookahead(MOTION_SETTLE_S, long.lookup)
        with Rider.on_link(long, None, early) as rider:
            assert rider.status().machine_id == "m1"
            assert rider.discovery is early.result()
    finally:
        daemon.stop()
