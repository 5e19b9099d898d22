"""A supervised daemon does not outlive its supervisor, and never starts without it."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ride_machine.service.core.scan.tuning import SUPERVISOR_PID_ENV, die_with_parent
from tests.procs import REPO, free_port, machine_cmd, write_zenoh_config

TIMEOUT_S = 30.0


def sim_daemon_cmd(tmp_path: Path) -> list[str]:
    """`machine run --sim` on a free loopback port with its own data dir and Zenoh config."""
    return machine_cmd(
        "run",
        "--sim",
        "--zenoh-config",
        str(write_zenoh_config(tmp_path)),
        "--listen",
        f"tcp/127.0.0.1:{free_port()}",
        "--data-dir",
        str(tmp_path / "data"),
    )


def test_die_with_parent_checks_the_parent_is_still_there() -> None:
    assert die_with_parent(os.getppid())
    assert not die_with_parent(os.getppid() + 999_999)


@pytest.mark.hazard("H04")
def test_daemon_refuses_to_run_when_its_supervisor_is_gone(tmp_path: Path) -> None:
    env = {**os.environ, SUPERVISOR_PID_ENV: "1"}  # init is not our parent
    cmd = sim_daemon_cmd(tmp_path)
    done = subprocess.run(
        cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=TIMEOUT_S, check=False
    )
    assert done.returncode == 1
    assert "supervisor_gone" in done.stderr


@pytest.mark.hazard("H04")
def test_daemon_gets_sigterm_when_its_parent_dies(tmp_path: Path) -> None:
    """A parent that starts the daemon the way the supervisor does, then is SIGKILLed."""
    daemon = sim_daemon_cmd(tmp_path)
    parent = f"""
import os, subprocess, sys
env = {{**os.environ, {SUPERVISOR_PID_ENV!r}: str(os.getpid())}}
child = subprocess.Popen({daemon!r}, env=env, stderr=subprocess.PIPE, text=True)
print(child.pid, flush=True)
for line in child.stderr:
    if "event=started" in line:
        print("started", flush=True)
        break
sys.stdin.read()
"""
    proc = subprocess.Popen(
        [sys.executable, "-c", parent],
        cwd=REPO,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    child_pid = int(proc.stdout.readline())
    pidfd = os.pidfd_open(child_pid)  # readable once the process has exited: the event
    ready: list[int] = []
    try:
        assert proc.stdout.readline().strip() == "started"
        proc.kill()
        proc.wait(TIMEOUT_S)
        ready, _, _ = select.select([pidfd], [], [], TIMEOUT_S)
    finally:
        os.close(pidfd)
        if proc.poll() is None:
            proc.kill()
        if Path(f"/proc/{child_pid}").exists() and not ready:
            os.kill(child_pid, signal.SIGKILL)
    assert ready, "the daemon outlived its supervisor"
