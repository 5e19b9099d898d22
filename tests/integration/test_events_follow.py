"""`follow_events` across a daemon restart and a cut link: the events published while the link
was down (the new run's `daemon_start`, a command) are read from the history, so the follower
misses none."""

from __future__ import annotations

import signal
import subprocess
import threading
from pathlib import Path

import pytest

from ride_machine.rider.client import Rider
from ride_machine.schema.events import Event
from tests import linkproxy
from tests.integration.support import STEP_TIMEOUT_S, fast_daemon
from tests.procs import Daemon, free_port, start_daemon, stop_process

pytestmark = pytest.mark.integration

RECONNECT_S = 30.0
"""Zenoh's own retry of the lost link (backing off), the history read, a loaded host."""


class Follower:
    """`rider.follow_events()` on a thread of its own, every event it yields kept in `seen`."""

    def __init__(self, rider: Rider) -> None:
        self.seen: list[Event] = []
        self._got = threading.Condition()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._follow, args=(rider,), daemon=True)
        self._thread.start()

    def _follow(self, rider: Rider) -> None:
        with rider:
            for event in rider.follow_events(timeout=0.2):
                if event is not None:
                    with self._got:
                        self.seen.append(event)
                        self._got.notify_all()
                if self._done.is_set():
                    return

    def wait_for(self, kind: str, count: int = 1, within: float = RECONNECT_S) -> None:
        with self._got:
            ok = self._got.wait_for(
                lambda: sum(e.kind == kind for e in self.seen) >= count, timeout=within
            )
        assert ok, [e.kind for e in self.seen]

    def stop(self) -> None:
        self._done.set()
        self._thread.join(10.0)

    def no_gap(self) -> bool:
        """Every seq once, in order."""
        seqs = [e.seq for e in self.seen]
        return seqs == list(range(1, len(seqs) + 1))


def test_a_follower_misses_nothing_when_the_daemon_restarts(tmp_path: Path) -> None:
    port = free_port()
    daemon = start_daemon(tmp_path, port=port)
    follower = Follower(daemon.rider(timeout=5.0))
    try:
        follower.wait_for("daemon_start", 1)
        assert daemon.stop() == 0
        follower.wait_for("daemon_stop", 1)
        daemon = start_daemon(tmp_path, port=port)  # same data dir, same endpoint
        assert daemon.cli("pause").returncode != 0  # refused: recorded as a command event
        follower.wait_for("command", 1)
    finally:
        follower.stop()
        daemon.stop()
    assert follower.no_gap(), [e.seq for e in follower.seen]
    kinds = [e.kind for e in follower.seen]
    assert kinds[:3] == ["daemon_start", "daemon_stop", "daemon_start"]


def test_a_follower_cut_off_reads_what_it_missed_once_the_machine_is_back(tmp_path: Path) -> None:
    """The link is cut (a proxy killed), the machine records a command meanwhile, and nothing
    happens after it: once the link is back, the follower reads that command from the history
    at once (the machine's liveliness token says it is back), not at some later event."""
    with fast_daemon(tmp_path) as daemon:
        port = free_port()
        link = start_proxy(port, daemon)
        endpoint = f"tcp/127.0.0.1:{port}"
        follower = Follower(Rider("m1", connect=[endpoint], zenoh_config_path=daemon.zenoh_config))
        try:
            follower.wait_for("daemon_start", within=STEP_TIMEOUT_S)
            stop_process(link, signal.SIGKILL)  # cut: the follower's link is gone
            assert daemon.cli("pause").returncode != 0  # a refused command: an event
            link = start_proxy(port, daemon)  # the link can come back
            follower.wait_for("command")
        finally:
            follower.stop()
            stop_process(link, signal.SIGKILL)
    assert follower.no_gap(), [e.seq for e in follower.seen]


def start_proxy(port: int, daemon: Daemon) -> subprocess.Popen[str]:
    return linkproxy.start(port, daemon.endpoint.rsplit(":", 1)[1], STEP_TIMEOUT_S)
