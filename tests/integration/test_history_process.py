"""The event history's own process (`[events] process = true`, the default) in a real daemon:
the daemon's child, named for `top`, and, when the daemon is killed, it writes every event the
daemon had sent it and then ends by itself."""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sqlite3
import time
from pathlib import Path

import pytest

from bench.common import children
from ride_machine.service.adapters.eventlog import EVENTS_FILE
from tests.procs import Daemon, start_daemon

pytestmark = pytest.mark.integration

COMMANDS = 20


def history_child(daemon: Daemon) -> int:
    """The daemon's one child process (started with its event log, before it serves)."""
    [child] = children(daemon.proc.pid)
    return child


def os_name(pid: int, want: str = "history", timeout: float = 10.0) -> str:
    """The process's name for the OS once it is `want`, or whatever it is after `timeout`."""
    deadline = time.monotonic() + timeout
    while True:
        with open(f"/proc/{pid}/comm") as fh:
            name = fh.read().strip()
        if name == want or time.monotonic() > deadline:
            return name
        time.sleep(0.01)


def written(daemon: Daemon, at_least: int) -> int:
    """The daemon's `events.written` once it reaches `at_least` (bounded: 10 s)."""
    deadline = time.monotonic() + 10.0
    with daemon.rider(supervise=False) as r:
        while True:
            events = r.diag().events
            assert events is not None
            if events.written >= at_least or time.monotonic() > deadline:
                return events.written
            r.status()  # one round trip between two looks, no sleep


def test_the_history_process_outlives_a_killed_daemon_only_to_write_what_it_was_sent(
    tmp_path: Path,
) -> None:
    daemon = start_daemon(tmp_path)
    try:
        child = history_child(daemon)
        with open(f"/proc/{child}/cmdline", "rb") as fh:
            assert b"service.adapters.history" in fh.read()
        # The child names itself once it runs: looked for until then (bounded), where one
        # look raced its start on a loaded host ('python' == 'history').
        assert os_name(child) == "history"
        with daemon.rider(supervise=False) as r:
            for _ in range(COMMANDS):
                r.check_home()
        assert written(daemon, 1 + COMMANDS) >= 1 + COMMANDS  # daemon_start and the commands
        ended = os.pidfd_open(child)
        daemon.proc.send_signal(signal.SIGKILL)
        daemon.proc.wait(10.0)
        try:
            # The pipe closed with the daemon: the process writes what it has and ends.
            assert select.select([ended], [], [], 10.0)[0] == [ended], "still running"
        finally:
            os.close(ended)
    finally:
        daemon.stop(signal.SIGKILL)
    with contextlib.closing(sqlite3.connect(daemon.data_dir / EVENTS_FILE)) as conn:
        kinds = [k for (k,) in conn.execute("SELECT kind FROM events ORDER BY seq")]
    assert kinds == ["daemon_start", *["command"] * COMMANDS]  # no daemon_stop: killed
