"""The image on the ride's own architecture (issue 57, point 2): a Revolution Pi Connect 4 /
Core is a Cortex-A72, arm64. Here, on an amd64 host, under qemu-user emulation: the image is
built for linux/arm64 from a locally made arm64 base (docs/deploy.md, "arm64"), every locked
wheel installed in its aarch64 build, and the supervised simulator runs in it; the Rider on
the host calibrates both axes, homes and rides a session through it.

Skipped, with the reason, where podman, an aarch64 binfmt handler (Debian's qemu-user-static)
or the arm64 base image is missing. Slow by nature (emulation is 5 to 20 times slower): its wall
time is in docs/deploy.md.
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest

from ride_machine.schema.status import MachineState, Status
from tests.deploy.engines import ENGINE, Done, build_args, build_context, engine
from tests.deploy.test_container import (
    calibrate,
    container,
    rider,
    run_rider,
    wait_healthy,
    world_late,
)
from tests.integration.support import TILT_LATE_WORLD, write_fast_config
from tests.procs import free_port

BUILD_TIMEOUT_S = 3600.0
pytestmark = [
    pytest.mark.integration,
    pytest.mark.container,
    pytest.mark.timeout(BUILD_TIMEOUT_S + 600),  # the first build: pip under emulation
]

ARM64_BASE = "localhost/python:3.11-slim-arm64"
IMAGE = "localhost/ride-machine:0.1.0-arm64"
BINFMT = Path("/proc/sys/fs/binfmt_misc/qemu-aarch64")
HEALTHY_TIMEOUT_S = 180.0
"""The supervisor, its daemon and the plant start in about 2 s natively; 10 to 40 emulated."""


def skip_reason() -> str | None:
    if ENGINE is None:
        return "no container engine (podman) on this host"
    if not BINFMT.exists() or not BINFMT.read_text().startswith("enabled"):
        return (
            "no aarch64 emulation: apt-get install qemu-user-static, then as root `mount -t"
            " binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc; update-binfmts --enable"
            " qemu-aarch64` (docs/deploy.md, arm64)"
        )
    done = subprocess.run([ENGINE, "image", "exists", ARM64_BASE], timeout=30.0, check=False)
    if done.returncode != 0:
        return (
            f"no arm64 base image {ARM64_BASE}: `ARCH=arm64 docker/make-base-image.sh podman"
            f" {ARM64_BASE}` (docs/deploy.md, arm64)"
        )
    return None


@pytest.fixture(scope="module")
def image(tmp_path_factory: pytest.TempPathFactory) -> str:
    reason = skip_reason()
    if reason:
        pytest.skip(reason)
    context = build_context(tmp_path_factory.mktemp("build-arm64"))
    replaced = engine("images", "-q", "--no-trunc", IMAGE).strip()
    done = subprocess.run(
        [str(ENGINE), "build", "--arch", "arm64", "--format", "docker", "--layers=false",
         "--build-arg", f"PYTHON_IMAGE={ARM64_BASE}", "-t", IMAGE, *build_args(), str(context)],
        capture_output=True, text=True, timeout=BUILD_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
    if replaced and replaced != engine("images", "-q", "--no-trunc", IMAGE).strip():
        engine("rmi", replaced, check=False)  # the last run's, now unnamed (unless in use)
    return IMAGE


def test_the_image_is_built_for_arm64_with_aarch64_wheels(image: str) -> None:
    (info,) = json.loads(engine("image", "inspect", image))
    assert (info["Os"], info["Architecture"]) == ("linux", "arm64")
    probe = (
        "import platform, zenoh, pydantic_core, msgpack; "
        "print(platform.machine(), zenoh.__file__, pydantic_core.__file__)"
    )
    out = engine("run", "--rm", image, "python", "-c", probe, timeout=300.0)
    machine, *modules = out.split()
    assert machine == "aarch64", out
    # the compiled parts are aarch64 builds, loaded (an amd64 .so would not import here)
    assert all(m.startswith("/opt/venv/") for m in modules), out


def ride(cli: Callable[..., Done], tries: int = 3) -> None:
    """Both axes calibrated, home, the default session to DONE. Emulated on a loaded host, the
    supervised simulator's world thread can come late and leave the tilt's analog standing:
    the machine then rightly faults the tilt (`TILT_LATE_WORLD`); only then, and only when the
    world itself counted a late step, it is all done again (as tests/deploy/test_container.py
    does for a calibration)."""
    for _ in range(tries):
        late = world_late(cli)
        calibrate(cli, "tilt")
        calibrate(cli, "rotate")
        homed = cli("home", "--wait")
        assert homed.returncode == 0, homed.stdout + homed.stderr
        session = cli("start", "--wait")
        if session.returncode == 0:
            return
        said = session.stdout + session.stderr
        assert any(code in said for code in TILT_LATE_WORLD), said
        assert world_late(cli) > late, f"the tilt faulted, the world never late: {said}"
    raise AssertionError(f"the session faulted by a late world {tries} times in a row")


def test_calibrate_home_and_a_session_on_arm64(image: str, tmp_path: Path) -> None:
    fast = write_fast_config(tmp_path)
    fast.chmod(0o644)
    port = free_port()
    name = f"ride-arm64-{os.getpid()}"
    with container(
        name, "-p", f"127.0.0.1:{port}:7447", "-v", f"{fast}:/etc/machine/machine.toml:ro", image
    ):
        wait_healthy(name, HEALTHY_TIMEOUT_S)
        endpoint = f"tcp/127.0.0.1:{port}"
        ride(functools.partial(run_rider, endpoint))
        status = Status.model_validate_json(
            rider(endpoint, "--json", "status").strip().splitlines()[-1]
        )
        assert status.state is MachineState.DONE, status
        assert status.calibrated.tilt and status.calibrated.rotate
        engine("stop", "-t", "30", name, timeout=120.0)
        assert engine("inspect", "--format", "{{.State.ExitCode}}", name).strip() == "0"
        logs = subprocess.run(
            [str(ENGINE), "logs", name], capture_output=True, text=True, timeout=30, check=True
        )
        assert "event=stopped code=0 outputs=safe" in logs.stderr, logs.stderr[-4000:]
