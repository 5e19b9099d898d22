"""`follow_events` across a daemon restart: the events published while the link was down
(the new run's `daemon_start`) are read from the history, so the follower misses none."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from schema.events import Event
from tests.procs import free_port, start_daemon

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
