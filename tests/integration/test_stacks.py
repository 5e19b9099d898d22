"""`kill -USR2 <pid>` asks a running `machine run` or `machine supervise` for every thread's
stack (service/signals.py): written to its log at once, and the machine runs on. A failed
test's report carries the stacks of the daemons still running (tests/conftest.py)."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ride_machine.schema.status import MachineState
from ride_machine.service.signals import STACKS_SIGNAL
from tests.integration.support import fast_daemon
from tests.procs import STACKS_MARK, catches, stop_process
from tests.reliability.support import start_machine

pytestmark = pytest.mark.integration


def test_a_running_daemon_writes_every_threads_stack_and_runs_on(tmp_path: Path) -> None:
    with fast_daemon(tmp_path) as daemon, daemon.rider(supervise=False) as r:
        before = r.diag().cycles
        stacks = "\n".join(daemon.stacks())
        # Every thread, the scan thread in its runner among them, not only the one that
        # happened to take the signal.
        assert stacks.count(STACKS_MARK) >= 5, daemon.log()[-3000:]
        assert "scan/runner.py" in stacks
        assert "Current thread" in stacks or "Thread 0x" in stacks
        # It runs on: it scans, answers, and stops as usual.
        assert r.status().state is not MachineState.FAULT_HW
        assert r.diag().cycles > before
        assert daemon.proc.poll() is None
    assert daemon.proc.returncode == 0


def test_a_supervisor_catches_the_signal_too(tmp_path: Path) -> None:
    daemon = start_machine(tmp_path, command="supervise")
    try:
        assert catches(daemon.proc.pid, STACKS_SIGNAL)
        assert STACKS_MARK in "\n".join(daemon.stacks())
        assert daemon.proc.poll() is None
    finally:
        assert stop_process(daemon.proc, signal.SIGTERM) == 0


def test_only_a_process_that_catches_the_signal_is_sent_it() -> None:
    """`Daemon.stacks` reads the handler from /proc first: the signal's default would kill a
    process that has none yet (one still loading its config)."""
    plain = subprocess.Popen(["sleep", "30"])
    caught = subprocess.Popen([sys.executable, "-c", _CATCHER], stdout=subprocess.PIPE, text=True)
    try:
        assert caught.stdout is not None and caught.stdout.readline().strip() == "ready"
        assert not catches(plain.pid, STACKS_SIGNAL)
        assert catches(caught.pid, STACKS_SIGNAL)
        assert not catches(caught.pid, signal.SIGUSR1)
    finally:
        for proc in (plain, caught):
            stop_process(proc, signal.SIGKILL)
    assert not catches(plain.pid, STACKS_SIGNAL)  # gone


_CATCHER = f"""
import signal, time
from ride_machine.service.signals import dump_stacks_on_signal
assert dump_stacks_on_signal(signal.Signals({int(STACKS_SIGNAL)}))
print("ready", flush=True)
time.sleep(30)
"""
