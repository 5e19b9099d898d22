"""The image in a real container engine, where present (podman): built as docs/deploy.md
says, run from the host, stopped safely mid-ride. compose.yaml on each engine and compose
tool: test_compose_engines.py.

Skipped, with the reason, without an engine or without the base image (no registry is reached:
make it with docker/make-base-image.sh, docs/deploy.md "No registry"). The image is built from a
copy of the build context; behind this host's TLS proxy pip's CA goes in as docker/pip/ca.crt.
The build is cached by the engine, so a run without changes to the package takes seconds; every
container, volume and network a test makes is removed afterwards, even when it fails.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status
from tests.deploy.engines import (
    BUILD_TIMEOUT_S,
    ENGINE,
    HEALTHY_TIMEOUT_S,
    STEP_TIMEOUT_S,
    UID,
    Done,
    build_args,
    engine,
    skip_reason,
)
from tests.integration.support import SPOILED, TILT_LATE_WORLD, write_fast_config
from tests.procs import free_port, rider_cmd, run_bounded

pytestmark = [pytest.mark.integration, pytest.mark.container]


def dangling() -> set[str]:
    return set(engine("images", "-q", "--no-trunc", "--filter", "dangling=true").split())


def test_the_documented_podman_build_leaves_no_unnamed_image(context: Path, tmp_path: Path) -> None:
    """Issue 57, reproduction 7: each `podman build` of changed sources left its builder stage
    behind as an unnamed image of about 300 MB (the layer cache's); docs/deploy.md's build has
    `--layers=false`. The sources change here (a line in the README the wheel carries), as
    they do between two releases; without `--layers=false` this fails."""
    reason = skip_reason()
    if reason:
        pytest.skip(reason)
    changed = tmp_path / "context"
    shutil.copytree(context, changed)
    with (changed / "README.md").open("a") as readme:
        readme.write(f"\n<!-- build {os.getpid()} {time.time_ns()} -->\n")
    tag = f"localhost/ride-machine:leftover-test-{os.getpid()}"
    before = dangling()
    try:
        engine(
            "build", "--format", "docker", "--layers=false", "-t", tag, *build_args(),
            str(changed), timeout=BUILD_TIMEOUT_S,
        )  # fmt: skip
        assert dangling() - before == set()
    finally:
        engine("rmi", tag, check=False)


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


def calibrate(rider: Callable[..., Done], axis: str, tries: int = 3) -> None:
    """`rider calibrate AXIS --wait` through `rider` (the host's CLI, or the one in a container);
    again when the machine refused a measurement that a stall of this (loaded) host spoiled
    (docs/homing.md), or stopped the tilt while the container's supervised world came late
    (`TILT_LATE_WORLD`, only when the world itself counted a late step meanwhile; the tilt is
    then calibrated again too, as its gain may be spoiled): the container is the subject here
    (run 100: CalibrateRotate's tilt move measured at 59.2°/s against 90°/s ± 30 %)."""
    for _ in range(tries):
        late = world_late(rider)
        done = rider("calibrate", axis, "--wait")
        if done.returncode == 0:
            return
        said = done.stdout + done.stderr
        if any(code in done.stdout for code in TILT_LATE_WORLD):
            assert world_late(rider) > late, f"the tilt stopped, the world never late: {said}"
            if axis != "tilt":
                calibrate(rider, "tilt", tries)
            continue
        assert any(code in done.stdout for code in SPOILED), said
    raise AssertionError(f"calibrate {axis}: a spoiled measurement {tries} times in a row")


def world_late(rider: Callable[..., Done]) -> int:
    """The simulated world's late steps so far (`rider --json sim world`)."""
    done = rider("--json", "sim", "world")
    assert done.returncode == 0, done.stdout + done.stderr
    return SimWorldState.model_validate_json(done.stdout.splitlines()[0]).late_steps or 0


def run_rider(
    endpoint: str, *args: str, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    cmd = rider_cmd("--connect", endpoint, "--machine", "m1", *args)
    return run_bounded(cmd, timeout=STEP_TIMEOUT_S, env={**os.environ, **(env or {})})


def rider(endpoint: str, *args: str, env: dict[str, str] | None = None) -> str:
    done = run_rider(endpoint, *args, env=env)
    assert done.returncode == 0, f"rider {args}: {done.returncode}\n{done.stdout}{done.stderr}"
    return done.stdout


def test_image_keeps_its_healthcheck_user_and_size(image: str) -> None:
    info = json.loads(engine("image", "inspect", image))[0]
    config = info["Config"]
    # podman shows it at the top level, docker under Config
    check = info.get("Healthcheck") or config.get("Healthcheck") or {}
    assert check.get("Test", [])[:2] == ["CMD", "/bin/sh"], "built without --format docker?"
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
        calibrate(functools.partial(run_rider, endpoint), "tilt")
        calibrate(functools.partial(run_rider, endpoint), "rotate")
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
