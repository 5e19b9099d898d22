"""The image and compose.yaml in a real container engine (podman), where one is present.

Skipped, with the reason, without podman or without the base image (no registry is reached: make
it with docker/make-base-image.sh, docs/deploy.md "No registry"). The build is cached by the
engine, so a run without changes to the package takes seconds; every container, volume and
network a test makes is removed afterwards, even when it fails.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from schema.status import MachineState, Status
from service.adapters.credentials import init_credentials
from tests.deploy import spec
from tests.integration.support import write_fast_config
from tests.procs import REPO, free_port, rider_cmd

ENGINE = shutil.which("podman")
BASE_IMAGE = "docker.io/library/python:3.11-slim"
IMAGE = "localhost/ride-machine:local"
BUILD_TIMEOUT_S = 300.0
STEP_TIMEOUT_S = 60.0
HEALTHY_TIMEOUT_S = 30.0
UID = 10001


def engine(*args: str, timeout: float = STEP_TIMEOUT_S, check: bool = True) -> str:
    assert ENGINE is not None
    done = subprocess.run(
        [ENGINE, *args], capture_output=True, text=True, timeout=timeout, check=False
    )
    if check and done.returncode != 0:
        raise AssertionError(f"podman {' '.join(args)}: exit {done.returncode}\n{done.stderr}")
    return done.stdout


def _skip_reason() -> str | None:
    if ENGINE is None:
        return "no container engine (podman) on this host"
    try:
        engine("info", timeout=30.0)
    except (AssertionError, subprocess.TimeoutExpired) as exc:
        return f"podman cannot run here: {exc}"
    done = subprocess.run([ENGINE, "image", "exists", BASE_IMAGE], timeout=30.0, check=False)
    if done.returncode != 0:
        return f"base image {BASE_IMAGE} missing (make it offline: docker/make-base-image.sh)"
    return None


pytestmark = [pytest.mark.integration, pytest.mark.container]


@pytest.fixture(scope="module")
def image() -> str:
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    args = ["build", "--format", "docker", "-t", IMAGE]
    # Behind this host's TLS proxy pip needs its CA: the build secret of the Dockerfile.
    ca = os.environ.get("PIP_CERT") or os.environ.get("SSL_CERT_FILE")
    if ca and Path(ca).is_file():
        args += ["--secret", f"id=pip-ca,src={ca}"]
    for name in ("PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_TRUSTED_HOST"):
        if os.environ.get(name):
            args += ["--build-arg", f"{name}={os.environ[name]}"]
    engine(*args, str(REPO), timeout=BUILD_TIMEOUT_S)
    return IMAGE


@contextlib.contextmanager
def container(name: str, *args: str) -> Iterator[str]:
    engine("run", "-d", "--name", name, *args)
    try:
        yield name
    finally:
        engine("rm", "-f", "-t", "0", name, check=False)


def wait_healthy(name: str, timeout: float = HEALTHY_TIMEOUT_S) -> float:
    """`podman healthcheck run` (no systemd here to run it periodically) until it passes."""
    start = time.monotonic()
    while True:
        done = subprocess.run(
            [str(ENGINE), "healthcheck", "run", name], capture_output=True, timeout=30, check=False
        )
        if done.returncode == 0:
            return time.monotonic() - start
        assert time.monotonic() - start < timeout, engine("logs", name, check=False)
        time.sleep(0.5)  # bounded retry of an external probe, not a settle


def rider(endpoint: str, *args: str, env: dict[str, str] | None = None) -> str:
    done = subprocess.run(
        rider_cmd("--connect", endpoint, "--machine", "m1", *args),
        capture_output=True,
        text=True,
        timeout=STEP_TIMEOUT_S,
        env={**os.environ, **(env or {})},
        check=False,
    )
    assert done.returncode == 0, f"rider {args}: {done.returncode}\n{done.stdout}{done.stderr}"
    return done.stdout


def test_image_keeps_its_healthcheck_user_and_size(image: str) -> None:
    info = json.loads(engine("image", "inspect", image))[0]
    config = info["Config"]
    # podman shows it at the top level, docker under Config
    check = info.get("Healthcheck") or config.get("Healthcheck") or {}
    assert check.get("Test", [])[:2] == ["CMD", "rider"], "built without --format docker?"
    assert config["User"] == f"{UID}:{UID}"
    assert config["StopSignal"] == "SIGTERM"
    assert not config.get("Volumes"), "an image VOLUME leaves anonymous volumes behind"


def test_container_runs_a_session_from_the_host_and_stops_safely(
    image: str, tmp_path: Path
) -> None:
    fast = write_fast_config(tmp_path)
    fast.chmod(0o644)
    port = free_port()
    name = f"ride-test-{os.getpid()}"
    with container(
        name,
        "-p",
        f"127.0.0.1:{port}:7447",
        "-v",
        f"{fast}:/etc/machine/machine.toml:ro",
        image,
    ):
        wait_healthy(name)
        endpoint = f"tcp/127.0.0.1:{port}"
        rider(endpoint, "calibrate", "tilt", "--wait")
        rider(endpoint, "calibrate", "rotate", "--wait")
        rider(endpoint, "home", "--wait")
        # Long enough (about 20 s) to be still under way when the next Rider process has
        # started on a loaded host and when SIGTERM comes: the default session (about 2 s at
        # the fast config) was DONE before `watch` attached, which then never saw RUNNING.
        session = tmp_path / "long.json"
        steps = [{"kind": "tilt", "degrees": 30}, {"kind": "rotate", "revolutions": 40}]
        session.write_text(json.dumps({"name": "long", "steps": steps}))
        rider(endpoint, "start", "--session", str(session))
        running = Status.model_validate_json(
            rider(
                endpoint, "--json", "watch", "--keys", "status", "--until", "RUNNING", "--for", "30"
            )
            .strip()
            .splitlines()[-1]
        )
        assert running.state is MachineState.RUNNING
        engine("stop", "-t", "10", name)  # SIGTERM mid-ride
        assert engine("inspect", "--format", "{{.State.ExitCode}}", name).strip() == "0"
        logs = subprocess.run(
            [str(ENGINE), "logs", name], capture_output=True, text=True, timeout=30, check=True
        )
        assert "event=signal signal=SIGTERM" in logs.stderr, logs.stderr
        assert "event=stopped code=0 outputs=safe" in logs.stderr, logs.stderr


@pytest.fixture
def project(image: str, tmp_path: Path) -> Iterator[tuple[Path, str]]:
    """compose.yaml's own files in a project directory, with credentials and a free UI port."""
    if shutil.which("podman-compose") is None and not (REPO / ".venv/bin/podman-compose").exists():
        pytest.skip("podman-compose is not installed (pip install podman-compose, the dev extra)")
    root = tmp_path / "site"
    for rel in ("machine.toml", "zenoh.json5", "zenoh/acl.json5", "docker/zenohd.json5"):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, root / rel)
    shutil.copy2(write_fast_config(tmp_path), root / "machine.toml")
    compose = yaml.safe_load((REPO / "compose.yaml").read_text())
    ui = free_port()
    compose["services"]["rider"]["ports"] = [f"127.0.0.1:{ui}:8080"]
    del compose["services"]["machine"]["build"]  # the fixture built it
    (root / "compose.yaml").write_text(yaml.safe_dump(compose, sort_keys=False))
    # As docs/deploy.md says: make the logins, readable by the containers' group.
    init_credentials(root / "secrets")
    for f in (root / "secrets").iterdir():
        os.chown(f, -1, UID)
        f.chmod(0o640)
    name = f"ridetest{os.getpid()}"
    try:
        yield root, name
    finally:
        compose_cmd(root, name, "down", "-v", check=False)


def compose_cmd(root: Path, name: str, *args: str, check: bool = True) -> str:
    tool = shutil.which("podman-compose") or str(REPO / ".venv/bin/podman-compose")
    done = subprocess.run(
        [tool, "-p", name, *args],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=STEP_TIMEOUT_S * 2,
        check=False,
    )
    if check and done.returncode != 0:
        raise AssertionError(
            f"podman-compose {args}: {done.returncode}\n{done.stdout}{done.stderr}"
        )
    return done.stdout


def in_rider(name: str, *args: str) -> str:
    return engine("exec", f"{name}_rider_1", "rider", *args)


def test_compose_up_down_keeps_the_calibration_and_no_anonymous_volume(
    project: tuple[Path, str],
) -> None:
    root, name = project
    volumes_before = set(engine("volume", "ls", "-q").split())
    compose_cmd(root, name, "up", "-d")
    wait_healthy(f"{name}_machine_1")
    in_rider(name, "calibrate", "tilt", "--wait")
    compose_cmd(root, name, "down")
    compose_cmd(root, name, "up", "-d")
    wait_healthy(f"{name}_machine_1")
    status = Status.model_validate_json(in_rider(name, "--json", "status").strip().splitlines()[-1])
    assert status.calibrated.tilt, "the data volume did not survive down/up"
    compose_cmd(root, name, "down")
    left = set(engine("volume", "ls", "-q").split()) - volumes_before
    assert left == {f"{name}_machine-data"}, f"volumes left by up/down: {left}"
    assert spec.load_compose()["volumes"] == {"machine-data": None}
