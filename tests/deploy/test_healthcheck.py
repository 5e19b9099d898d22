"""The exact HEALTHCHECK commands of the Dockerfile and compose.yaml, run against real daemons.

Only the endpoint changes: the container's `tcp/127.0.0.1:7447` becomes the test daemon's free
loopback port. Exit 0 when the daemon answers, 3 (no reply) when nothing listens.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from rider.cli import EXIT_NO_REPLY, EXIT_OK
from rider.client import Rider
from tests.deploy import spec
from tests.procs import REPO, Daemon, free_port, running_daemon, start_daemon

pytestmark = pytest.mark.integration

CHECK_TIMEOUT_S = 30.0
"""Bound for one healthcheck process (Docker's own is tighter; this one only ends a hang)."""

CONTAINER_ENDPOINT = "tcp/127.0.0.1:7447"

SEE_BOTH_TIMEOUT_S = 20.0

GOSSIP_CONFIG = """{
  mode: "peer",
  scouting: { multicast: { enabled: false }, gossip: { enabled: true } },
  transport: { link: { tx: { lease: 1000, keep_alive: 4 } } },
}
"""


def image_check() -> list[str]:
    (check,) = [i.args for i in spec.final_stage(spec.dockerfile()) if i.keyword == "HEALTHCHECK"]
    _, rest = spec.split_options(check)
    return spec.exec_form(rest.removeprefix("CMD "))


def compose_check() -> list[str]:
    return spec.healthcheck_argv(spec.service(spec.load_compose(), "machine"))


CHECKS = {"Dockerfile": image_check, "compose.yaml": compose_check}


def run_check(argv: list[str], endpoint: str) -> subprocess.CompletedProcess[str]:
    assert CONTAINER_ENDPOINT in argv, argv
    argv = [endpoint if a == CONTAINER_ENDPOINT else a for a in argv]
    return subprocess.run(
        spec.host_argv(argv, {}),
        capture_output=True,
        text=True,
        timeout=CHECK_TIMEOUT_S,
        cwd=REPO,
        check=False,
    )


@pytest.fixture(scope="module")
def m1(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    with running_daemon(tmp_path_factory.mktemp("healthcheck")) as daemon:
        yield daemon


@pytest.mark.parametrize("source", CHECKS)
def test_healthcheck_passes_when_the_daemon_answers(source: str, m1: Daemon) -> None:
    done = run_check(CHECKS[source](), m1.endpoint)
    assert done.returncode == EXIT_OK, done.stdout + done.stderr
    assert "m1" in done.stdout


@pytest.mark.parametrize("source", CHECKS)
def test_healthcheck_fails_when_nothing_answers(source: str) -> None:
    done = run_check(CHECKS[source](), f"tcp/127.0.0.1:{free_port()}")
    assert done.returncode == EXIT_NO_REPLY, done.stdout + done.stderr


def test_healthcheck_stays_healthy_with_a_second_machine_on_the_network(tmp_path: Path) -> None:
    """With gossip on (as in zenoh.json5) a Rider connected to m1 also learns of m2, as it
    would through a site router; an unnamed `status` could then exit 4 (ambiguous). The
    healthcheck names its machine, so it cannot."""
    gossip = tmp_path / "gossip.json5"
    gossip.write_text(GOSSIP_CONFIG)
    use_gossip = ["--zenoh-config", str(gossip)]  # the last --zenoh-config wins
    m1 = start_daemon(tmp_path, "m1", extra=use_gossip)
    m2: Daemon | None = None
    try:
        m2 = start_daemon(tmp_path, "m2", extra=[*use_gossip, "--connect", m1.endpoint])
        seen: set[str] = set()
        deadline = time.monotonic() + SEE_BOTH_TIMEOUT_S
        with Rider(None, connect=[m1.endpoint], zenoh_config_path=gossip) as watcher:
            for change in watcher.follow_machines(timeout=0.5):
                if change is not None and change[1]:
                    seen.add(change[0])
                if seen >= {"m1", "m2"} or time.monotonic() > deadline:
                    break
        assert seen >= {"m1", "m2"}, f"m2 never became visible through m1: {seen}"
        for _ in range(3):
            done = run_check(image_check(), m1.endpoint)
            assert done.returncode == EXIT_OK, done.stdout + done.stderr
    finally:
        if m2 is not None:
            m2.stop()
        m1.stop()
