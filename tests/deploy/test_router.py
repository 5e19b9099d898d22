"""The router service of docker/compose.router.yaml, run through a replica of the published Zenoh
image's entrypoint (tests/deploy/zenoh-entrypoint.sh: `echo " * Starting: /$BINARY $@"; exec
/$BINARY $@`, unquoted) with a stand-in zenohd (tests/deploy/zenohd.py).

The service's own entrypoint, script and config are used, their container paths mapped to host
files; the router reaches a real daemon on loopback that runs the authenticated profile, and a
site Rider reaches the machine through the router. No engine and no root needed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rider.cli import EXIT_OK
from schema.status import Status
from service.adapters.credentials import DICTIONARY, init_credentials, password_file
from tests.deploy import spec
from tests.deploy.test_topology import Child
from tests.procs import REPO, Daemon, free_port, rider_cmd, start_daemon

pytestmark = pytest.mark.integration

ROUTER_OVERRIDE = REPO / "docker" / "compose.router.yaml"
REPLICA = Path(__file__).with_name("zenoh-entrypoint.sh")
READY_TIMEOUT_S = 30.0
STEP_TIMEOUT_S = 60.0
SITE_CLIENT = REPO / "docker" / "rider-client.json5"


def router_service() -> dict[str, Any]:
    return spec.service(spec.load_compose(ROUTER_OVERRIDE), "router")


def host_files(tmp: Path, mapping: dict[str, str]) -> None:
    """Copies of the router's mounted files with every container path in `mapping` replaced."""
    for m in spec.mounts(router_service()):
        text = (REPO / m.source).read_text()
        for container, host in mapping.items():
            text = text.replace(container, host)
        dest = Path(mapping[m.target])
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_text(text)


@pytest.fixture
def site(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Path, Daemon]]:
    """The secrets as `machine credentials init` makes them, and a machine on loopback with the
    authenticated profile (as compose.yaml runs it)."""
    secrets = tmp_path / "secrets"
    init_credentials(secrets)
    monkeypatch.setenv("MACHINE_ZENOH_DICTIONARY_FILE", str(secrets / DICTIONARY))
    extra = ["--zenoh-config", str(REPO / "zenoh" / "acl.json5")]
    daemon = start_daemon(tmp_path, extra=extra, wait=False)
    try:
        yield secrets, daemon
    finally:
        daemon.stop()


def start_router(tmp: Path, secrets: Path, machine_endpoint: str) -> tuple[Child, int]:
    """The service's entrypoint with its environment; the image's /entrypoint.sh is the replica
    and zenohd the stand-in. Returns the child and the router's port."""
    svc = router_service()
    port = free_port()
    run_dir = tmp / "run-zenohd"
    mapping = {
        "/etc/zenoh/zenohd-start.sh": str(tmp / "etc" / "zenohd-start.sh"),
        "/etc/zenoh/zenohd.json5": str(tmp / "etc" / "zenohd.json5"),
        "/run/zenohd": str(run_dir),
        "/run/secrets": str(secrets),
        "/entrypoint.sh": str(REPLICA),
        # the compose network's names and the published port, as loopback here
        "tcp/machine:7447": machine_endpoint,
        "tcp/0.0.0.0:7447": f"tcp/127.0.0.1:{port}",
    }
    host_files(tmp, mapping)
    zenohd = tmp / "bin" / "zenohd"
    zenohd.parent.mkdir()
    zenohd.write_text(f'#!/bin/sh\nexec {sys.executable} -m tests.deploy.zenohd "$@"\n')
    zenohd.chmod(0o755)
    argv = [mapping.get(a, a) for a in svc["entrypoint"]]
    shell = shutil.which("busybox")  # the image's shell is busybox's ash
    if shell is not None and argv[0] == "/bin/sh":
        argv = [shell, "sh", *argv[1:]]
    env = {**os.environ, **spec.environment(svc), "BINARY": str(zenohd).lstrip("/")}
    return Child.start("router", argv, env), port


def test_router_starts_through_the_image_entrypoint_without_spaces_or_secrets(
    tmp_path: Path, site: tuple[Path, Daemon]
) -> None:
    secrets, daemon = site
    router, port = start_router(tmp_path, secrets, daemon.endpoint)
    try:
        router.wait_line("ready", READY_TIMEOUT_S)
        argv = json.loads(router.wait_line("argv ").removeprefix("argv "))
        assert argv == ["-c", str(tmp_path / "run-zenohd" / "zenohd.json5")]
        rendered = tmp_path / "run-zenohd" / "zenohd.json5"
        assert rendered.stat().st_mode & 0o077 == 0, "the config with the password: owner only"
        # The machine login reaches the router through its config: a site Rider logs in to the
        # router and gets the machine's status through it.
        env = {
            **os.environ,
            "RIDER_ZENOH_USER": "rider",
            "RIDER_ZENOH_PASSWORD_FILE": str(password_file(secrets, "rider")),
        }
        site_rider = rider_cmd(
            "--zenoh-config", str(SITE_CLIENT), "--connect", f"tcp/127.0.0.1:{port}", "-m", "m1"
        )
        # The daemon starts beside the router and the router retries its connect: ask until
        # the machine answers through it (bounded).
        deadline = time.monotonic() + READY_TIMEOUT_S
        while True:
            done = subprocess.run(
                [*site_rider, "--timeout", "5", "--json", "status"],
                capture_output=True, text=True, timeout=STEP_TIMEOUT_S, env=env, check=False,
            )  # fmt: skip
            if done.returncode == EXIT_OK or time.monotonic() > deadline:
                break
        assert done.returncode == EXIT_OK, done.stdout + done.stderr + router.log() + daemon.log()
        status = Status.model_validate_json(done.stdout.strip().splitlines()[-1])
        assert status.machine_id == "m1"
    finally:
        assert router.stop() == 0, router.log()
    password = password_file(secrets, "machine").read_text().strip()
    assert password not in router.log(), "the router's log shows the machine password"
    assert " * Starting: /" in router.log()  # the replica's echo ran


def test_the_folded_cfg_argument_of_round_two_breaks_in_the_entrypoint(tmp_path: Path) -> None:
    """Why the router has a config file: a `--cfg` value with a space, as the router service
    passed it before, reaches zenohd in pieces and is echoed, password and all."""
    zenohd = tmp_path / "zenohd"
    zenohd.write_text(f'#!/bin/sh\nexec {sys.executable} -m tests.deploy.zenohd "$@"\n')
    zenohd.chmod(0o755)
    login = "transport/auth/usrpwd:{user:'machine',password:'s3cret', dictionary_file:'/x'}"
    done = subprocess.run(
        [str(REPLICA), "-c", str(REPO / "docker" / "zenohd.json5"), "--cfg", login],
        capture_output=True, text=True, timeout=STEP_TIMEOUT_S, cwd=REPO, check=False,
        env={**os.environ, "BINARY": str(zenohd).lstrip("/")},
    )  # fmt: skip
    assert "s3cret" in done.stdout.splitlines()[0]  # the echo
    argv = json.loads(done.stdout.splitlines()[1].removeprefix("argv "))
    assert argv[3:] == [
        "transport/auth/usrpwd:{user:'machine',password:'s3cret',",
        "dictionary_file:'/x'}",
    ]
    assert done.returncode == 2, done.stderr  # zenohd refuses the stray argument
