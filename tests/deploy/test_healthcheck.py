"""The HEALTHCHECK of the Dockerfile and the machine service's of compose.yaml, run as the engine
runs them (`/bin/sh -c …`) against a real daemon that touches its heartbeat file.

Only the file's container path (`/dev/shm/machine.heartbeat`) becomes a file of this test. The
check passes while the scan loop cycles, fails once the daemon is frozen (SIGSTOP) for longer
than the check allows, passes again when it runs on, and fails at once when the daemon has
stopped (the file is removed).
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.service.adapters.heartbeat import HEARTBEAT_FILE_ENV
from tests.deploy import spec
from tests.procs import Daemon, start_daemon

pytestmark = pytest.mark.integration

CHECK_TIMEOUT_S = 30.0
"""Bound for one healthcheck process (Docker's own is tighter; this one only ends a hang)."""
CONTAINER_FILE = "/dev/shm/machine.heartbeat"
STALE_TIMEOUT_S = 30.0
"""Bound for a frozen daemon's file to age past the check (the check allows 6 s)."""


def image_check() -> list[str]:
    (check,) = [i.args for i in spec.image(spec.dockerfile()) if i.keyword == "HEALTHCHECK"]
    _, rest = spec.split_options(check)
    return spec.exec_form(rest.removeprefix("CMD "))


def compose_check() -> list[str]:
    """CMD-SHELL, as docker and podman run it: `/bin/sh -c STRING`."""
    kind, script = spec.service(spec.load_compose(), "machine")["healthcheck"]["test"]
    assert kind == "CMD-SHELL"
    return ["/bin/sh", "-c", script]


CHECKS = {"Dockerfile": image_check, "compose.yaml": compose_check}


def run_check(argv: list[str], heartbeat: Path) -> int:
    assert any(CONTAINER_FILE in a for a in argv), argv
    argv = [a.replace(CONTAINER_FILE, str(heartbeat)) for a in argv]
    done = subprocess.run(argv, capture_output=True, timeout=CHECK_TIMEOUT_S, check=False)
    return done.returncode


def wait_check(argv: list[str], heartbeat: Path, healthy: bool, timeout: float) -> float:
    """Seconds until the check gives the wanted answer (a bounded poll of an outside probe)."""
    start = time.monotonic()
    while (run_check(argv, heartbeat) == 0) != healthy:
        assert time.monotonic() - start < timeout, f"healthy={not healthy} for {timeout:g} s"
        time.sleep(0.25)
    return time.monotonic() - start


@pytest.fixture(scope="module")
def m1(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Daemon, Path]]:
    tmp = tmp_path_factory.mktemp("healthcheck")
    heartbeat = tmp / "machine.heartbeat"
    daemon = start_daemon(tmp, env={HEARTBEAT_FILE_ENV: str(heartbeat)})
    try:
        yield daemon, heartbeat
    finally:
        daemon.stop()


@pytest.mark.parametrize("source", CHECKS)
def test_healthcheck_passes_while_the_scan_loop_cycles(
    source: str, m1: tuple[Daemon, Path]
) -> None:
    daemon, heartbeat = m1
    wait_check(CHECKS[source](), heartbeat, healthy=True, timeout=STALE_TIMEOUT_S)
    assert daemon.has_logged(f"event=heartbeat_file path={heartbeat}")


def test_a_frozen_daemon_turns_unhealthy_and_recovers(m1: tuple[Daemon, Path]) -> None:
    daemon, heartbeat = m1
    check = compose_check()
    wait_check(check, heartbeat, healthy=True, timeout=STALE_TIMEOUT_S)
    os.kill(daemon.proc.pid, signal.SIGSTOP)
    try:
        stale_after = wait_check(check, heartbeat, healthy=False, timeout=STALE_TIMEOUT_S)
        assert run_check(image_check(), heartbeat) != 0
    finally:
        os.kill(daemon.proc.pid, signal.SIGCONT)
    assert stale_after >= 4.0, "the check allows about 6 s of silence, not less"
    wait_check(check, heartbeat, healthy=True, timeout=STALE_TIMEOUT_S)


def test_healthcheck_fails_when_nothing_runs(tmp_path: Path) -> None:
    for source, check in CHECKS.items():
        assert run_check(check(), tmp_path / "machine.heartbeat") != 0, source


def test_a_stopped_daemon_is_unhealthy_at_once(tmp_path: Path) -> None:
    heartbeat = tmp_path / "machine.heartbeat"
    daemon = start_daemon(tmp_path, env={HEARTBEAT_FILE_ENV: str(heartbeat)})
    try:
        wait_check(compose_check(), heartbeat, healthy=True, timeout=STALE_TIMEOUT_S)
    finally:
        assert daemon.stop() == 0
    assert not heartbeat.exists()
    assert run_check(compose_check(), heartbeat) != 0
