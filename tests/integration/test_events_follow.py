"""`follow_events` across a daemon restart: the events published while the link was down
(the new run's `daemon_start`) are read from the history, so the follower misses none."""

from __future__ import annotations

import signal
import subprocess
import threading
from pathlib import Path

import pytest

from rider.client import Rider
from schema.events import Event
from tests import linkproxy
from tests.integration.support import STEP_TIMEOUT_S, fast_daemon
from tests.procs import Daemon, free_port, start_daemon, stop_process

pytestmark = pytest.mark.integration


def test_a_follower_misses_nothing_when_the_daemon_restarts(tmp_path: Path) -> None:
    port = free_port()
    daemon = start_daemon(tmp_path, port=port)
    seen: list[Event] = []
    got = threading.Condition()
    done = threading.Event()

    def follow() -> None:
        with daemon.rider(timeout=5.0) as rider:
            for event in rider.follow_events(timeout=0.2):
                if event is not None:
                    with got:
                        seen.append(event)
                        got.notify_all()
                if done.is_set():
                    return

    def wait_for(kind: str, count: int) -> None:
        with got:
            ok = got.wait_for(lambda: sum(e.kind == kind for e in seen) >= count, timeout=30.0)
        assert ok, [e.kind for e in seen]

    follower = threading.Thread(target=follow, daemon=True)
    follower.start()
    try:
        wait_for("daemon_start", 1)
        assert daemon.stop() == 0
        wait_for("daemon_stop", 1)
        daemon = start_daemon(tmp_path, port=port)  # same data dir, same endpoint
        assert daemon.cli("pause").returncode != 0  # refused: recorded as a command event
        wait_for("command", 1)
    finally:
        done.set()
        daemon.stop()
        follower.join(10.0)
    seqs = [e.seq for e in seen]
    assert seqs == list(range(1, len(seqs) + 1))  # every seq once, in order: no gap
    kinds = [e.kind for e in seen]
    assert kinds[:3] == ["daemon_start", "daemon_stop", "daemon_start"]


def test_a_follower_cut_off_reads_what_it_missed_once_the_machine_is_back(tmp_path: Path) -> None:
    """The link is cut (a proxy killed), the machine records a command meanwhile, and nothing
    happens after it: once the link is back, the follower reads that command from the history
    at once (the machine's liveliness token says it is back), not at some later event."""
    with fast_daemon(tmp_path) as daemon:
        port = free_port()
        link = start_proxy(port, daemon)
        seen: list[Event] = []
        got = threading.Condition()
        done = threading.Event()

        def follow() -> None:
            endpoint = f"tcp/127.0.0.1:{port}"
            with Rider("m1", connect=[endpoint], zenoh_config_path=daemon.zenoh_config) as r:
                for event in r.follow_events(timeout=0.2):
                    if event is not None:
                        with got:
                            seen.append(event)
                            got.notify_all()
                    if done.is_set():
                        return

        def wait_for(kind: str, within: float) -> bool:
            with got:
                return got.wait_for(lambda: any(e.kind == kind for e in seen), timeout=within)

        follower = threading.Thread(target=follow, daemon=True)
        follower.start()
        try:
            assert wait_for("daemon_start", STEP_TIMEOUT_S), [e.kind for e in seen]
            stop_process(link, signal.SIGKILL)  # cut: the follower's link is gone
            assert daemon.cli("pause").returncode != 0  # a refused command: an event
            link = start_proxy(port, daemon)  # the link can come back
            assert wait_for("command", RECONNECT_S), [e.kind for e in seen]
        finally:
            done.set()
            stop_process(link, signal.SIGKILL)
            follower.join(10.0)
    seqs = [e.seq for e in seen]
    assert seqs == list(range(1, len(seqs) + 1)), seqs  # every seq once, in order


RECONNECT_S = 30.0
"""Zenoh's own retry of the lost link (backing off), the history read, a loaded host."""


def start_proxy(port: int, daemon: Daemon) -> subprocess.Popen[str]:
    return linkproxy.start(port, daemon.endpoint.rsplit(":", 1)[1], STEP_TIMEOUT_S)
