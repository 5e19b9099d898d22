"""A stream of SIGTERMs (a process manager and an operator's Ctrl-C at once, a script in a loop)
stops `machine run` and `machine supervise` once and cleanly: before the signal thread, the
second signal's handler, run inside the first one's logging, waited for a lock its own thread
held, and the daemon froze with its scan stopped (10 of 10 tries)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from tests.probes import signal_storm
from tests.procs import STOP_TIMEOUT_S, Daemon
from tests.reliability.support import start_machine, supervisor_child


def stopped_once(daemon: Daemon) -> str:
    """The storm, then the exit (bounded): the log, once the process has exited 0."""
    assert signal_storm(daemon.proc.pid) > 1
    try:
        code = daemon.proc.wait(STOP_TIMEOUT_S)
    except Exception:
        daemon.stop(signal.SIGKILL)
        raise
    assert code == 0, daemon.log()[-3000:]
    return daemon.log()


@pytest.mark.integration
def test_a_signal_storm_stops_the_daemon_once_and_cleanly(tmp_path: Path) -> None:
    log = stopped_once(start_machine(tmp_path))
    assert log.count("event=signal ") == 1
    [stopped] = [line for line in log.splitlines() if "event=stopped" in line]
    assert "code=0 outputs=safe" in stopped


@pytest.mark.integration
def test_a_signal_storm_stops_the_supervisor_and_its_daemon_once(tmp_path: Path) -> None:
    supervised = start_machine(tmp_path, command="supervise")
    child = supervisor_child(supervised)
    log = stopped_once(supervised)
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)
    assert log.count("event=signal ") == 2  # the supervisor's, and the SIGTERM it sent its child
    assert "event=stopped code=0 outputs=safe" in log  # the daemon's own clean shutdown
    assert "event=supervisor_stopped code=0" in log
