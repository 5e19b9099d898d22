"""compose.yaml run by each compose tool on its engine, where present: podman-compose 1.0.3
(Debian) and 1.6 (PyPI) on podman, docker-compose 1.29 on Debian's docker (the classic
builder). Each run as docs/deploy.md says: the logins made with the image, `up -d`, both
services healthy with the hardening in effect, the calibration kept over down/up; without the
logins, the tool stops or the logins check exits 1 (issue 57, reproduction 5). Nothing of the
project is left afterwards. Skipped, with the reason, where a tool or its engine is missing.
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from ride_machine.schema.status import Status
from tests.deploy import spec
from tests.deploy.engines import (
    BASE_IMAGE,
    BUILD_TIMEOUT_S,
    DOCKER,
    ENGINE,
    HEALTHY_TIMEOUT_S,
    IMAGE,
    STEP_TIMEOUT_S,
    UID,
    engine_run,
    run_engine,
    skip_reason,
)
from tests.deploy.test_container import calibrate
from tests.integration.support import write_fast_config
from tests.procs import REPO, free_port

pytestmark = [pytest.mark.integration, pytest.mark.container]


@dataclass(frozen=True)
class ComposeTool:
    """A compose implementation and the engine it drives."""

    label: str
    argv: tuple[str, ...]
    engine: str
    build: bool
    """`up --build` (docker-compose builds with the classic builder); podman-compose takes the
    image the `image` fixture built (`podman-compose build` would drop the healthcheck)."""


TOOLS = [
    ComposeTool("podman-compose-debian", ("/usr/bin/podman-compose",), "podman", False),
    ComposeTool("podman-compose-pypi", (str(REPO / ".venv/bin/podman-compose"),), "podman", False),
    ComposeTool("docker-compose", ("/usr/bin/docker-compose",), "docker", True),
]


def _dockerskip_reason() -> str | None:
    if DOCKER is None:
        return "no docker engine on this host"
    done = subprocess.run([DOCKER, "info"], capture_output=True, timeout=30, check=False)
    if done.returncode != 0:
        return "dockerd is not running (docs/deploy.md: start Debian's dockerd)"
    done = subprocess.run(
        [DOCKER, "image", "inspect", BASE_IMAGE], capture_output=True, check=False
    )
    if done.returncode != 0:
        return f"base image {BASE_IMAGE} missing in docker (docker/make-base-image.sh docker)"
    return None


@dataclass
class Site:
    """A project directory made as docs/deploy.md says, run by one compose tool."""

    tool: ComposeTool
    root: Path
    name: str

    def compose(self, *args: str, check: bool = True) -> str:
        done = subprocess.run(
            [*self.tool.argv, "-p", self.name, *args], cwd=self.root, capture_output=True,
            text=True, timeout=BUILD_TIMEOUT_S, check=False,
        )  # fmt: skip
        if check and done.returncode != 0:
            raise AssertionError(f"{self.tool.label} {args}: {done.returncode}\n{done.stderr}")
        return done.stdout

    def engine(self, *args: str, check: bool = True) -> str:
        return run_engine(self.tool.engine, *args, check=check)

    def container(self, service: str) -> str:
        return f"{self.name}_{service}_1"

    def wait_healthy(self, service: str) -> None:
        """Until the engine calls the container healthy: podman runs the check on request
        (no systemd here), docker runs it itself every interval."""
        name, start = self.container(service), time.monotonic()
        while True:
            if self.tool.engine == "podman":
                binary = str(ENGINE)
                check = subprocess.run(
                    [binary, "healthcheck", "run", name], timeout=30, check=False
                )
                ok = check.returncode == 0
            else:
                state = self.engine("inspect", "-f", "{{.State.Health.Status}}", name).strip()
                ok = state == "healthy"
            if ok:
                return
            assert time.monotonic() - start < HEALTHY_TIMEOUT_S * 2, self.engine("logs", name)
            time.sleep(1.0)  # bounded retry of an outside probe, not a settle

    def unnamed_images(self) -> set[str]:
        return set(self.engine("images", "-q", "--no-trunc", "--filter", "dangling=true").split())

    def leftovers(self) -> list[str]:
        label = f"label=com.docker.compose.project={self.name}"
        names = self.engine("ps", "-a", "--filter", label, "--format", "{{.Names}}").split()
        networks = self.engine("network", "ls", "--format", "{{.Name}}").split()
        volumes = self.engine("volume", "ls", "--format", "{{.Name}}").split()
        return names + [n for n in networks + volumes if n.startswith(f"{self.name}_")]

    def remove_leftovers(self) -> None:
        label = f"label=com.docker.compose.project={self.name}"
        for c in self.engine("ps", "-a", "-q", "--filter", label, check=False).split():
            self.engine("rm", "-f", c, check=False)
        for n in self.engine("network", "ls", "--format", "{{.Name}}", check=False).split():
            if n.startswith(f"{self.name}_"):
                self.engine("network", "rm", n, check=False)
        for v in self.engine("volume", "ls", "--format", "{{.Name}}", check=False).split():
            if v.startswith(f"{self.name}_"):
                self.engine("volume", "rm", "-f", v, check=False)


@pytest.fixture(params=TOOLS, ids=lambda t: t.label)
def site(request: pytest.FixtureRequest, context: Path, tmp_path: Path) -> Iterator[Site]:
    """compose.yaml with the build context, the logins made from the image as the docs say."""
    tool: ComposeTool = request.param
    if not Path(tool.argv[0]).exists():
        pytest.skip(f"{tool.label} is not installed")
    reason = skip_reason() if tool.engine == "podman" else _dockerskip_reason()
    if reason:
        pytest.skip(reason)
    if tool.engine == "podman":
        request.getfixturevalue("image")
    root = tmp_path / "site"
    shutil.copytree(context, root)
    shutil.copy2(write_fast_config(tmp_path), root / "machine.toml")
    shutil.copy2(REPO / "docker" / "check_logins.py", root / "docker")  # the logins check
    compose = yaml.safe_load((REPO / "compose.yaml").read_text())
    compose["services"]["rider"]["ports"] = [f"127.0.0.1:{free_port()}:8080"]
    (root / "compose.yaml").write_text(yaml.safe_dump(compose, sort_keys=False))
    site = Site(tool, root, f"ridetest{os.getpid()}{tool.engine}")
    unnamed = site.unnamed_images()
    try:
        if tool.build:
            site.compose("build")  # docker-compose 1.29: the classic builder
        # docs/deploy.md: the logins made with the image on a host without the package
        site.engine(
            "run", "--rm", "-u", f"{os.getuid()}:{os.getgid()}", "-v", f"{root}:/site",
            "-w", "/site", IMAGE, "machine", "credentials", "init", "secrets",
        )  # fmt: skip
        for f in [root / "secrets", *(root / "secrets").iterdir()]:
            os.chown(f, -1, UID)
            f.chmod(0o710 if f.is_dir() else 0o640)  # docs/deploy.md: `chgrp 10001 secrets …`
        yield site
    finally:
        site.compose("down", "-v", check=False)
        # podman-compose 1.0.3's `down` leaves the project's network: the test removes whatever
        # is left, then checks that nothing of its project remains.
        site.remove_leftovers()
        assert not site.leftovers(), f"{tool.label}: could not remove {site.leftovers()}"
        # The classic builder keeps each stage, and the image its build replaced, unnamed
        # (docs/deploy.md: `docker image prune -f`); only those this test made go.
        for image in site.unnamed_images() - unnamed:
            site.engine("rmi", image, check=False)


HARDENING_PROBE = (
    "grep -E '^(CapEff|NoNewPrivs):' /proc/1/status; "
    "touch /etc/machine/x 2>/dev/null && echo root=writable || echo root=read-only; "
    "cat /sys/fs/cgroup/memory.max 2>/dev/null || cat /sys/fs/cgroup/memory/memory.limit_in_bytes; "
    "cat /sys/fs/cgroup/pids.max 2>/dev/null || cat /sys/fs/cgroup/pids/pids.max"
)  # cgroup v2, or v1


def hardening(site: Site, service: str) -> list[str]:
    """What the running container got: capabilities, no_new_privs, root, memory, pids."""
    out = site.engine("exec", site.container(service), "sh", "-c", HARDENING_PROBE)
    return [" ".join(line.split()) for line in out.splitlines()]


def test_compose_services_turn_healthy_and_keep_the_calibration(site: Site) -> None:
    site.compose("up", "-d")
    site.wait_healthy("machine")
    site.wait_healthy("rider")
    written = spec.load_compose()
    for service in ("machine", "rider"):
        svc = spec.service(written, service)
        memory = int(svc["mem_limit"].removesuffix("m")) << 20
        # Debian's podman-compose 1.0.3 drops pids_limit: podman's default bound (2048) holds
        pids = 2048 if site.tool.label == "podman-compose-debian" else svc["pids_limit"]
        assert hardening(site, service) == [
            "CapEff: 0000000000000000", "NoNewPrivs: 1", "root=read-only", str(memory), str(pids)
        ], f"{site.tool.label}: {service}"  # fmt: skip
    rider = site.container("rider")
    calibrate(functools.partial(engine_run, site.tool.engine, "exec", rider, "rider"), "tilt")
    site.compose("down")
    site.compose("up", "-d")
    site.wait_healthy("machine")
    out = site.engine("exec", rider, "rider", "--json", "status")
    status = Status.model_validate_json(out.strip().splitlines()[-1])
    assert status.calibrated.tilt, "the data volume did not survive down/up"


def test_compose_without_the_logins_stops_or_its_check_exits_with_one(site: Site) -> None:
    """Issue 57, reproduction 5, on the engine: `rm -rf secrets; <tool> up -d`. podman-compose
    1.6 and docker-compose exit non-zero at once; Debian's podman-compose 1.0.3 ignores every
    podman error and exits 0 (docs/deploy.md), but its `logins` container, like the others',
    has exited 1 naming each missing file and the command that makes them; nothing else runs."""
    shutil.rmtree(site.root / "secrets")
    done = subprocess.run(
        [*site.tool.argv, "-p", site.name, "up", "-d"], cwd=site.root, capture_output=True,
        text=True, timeout=STEP_TIMEOUT_S * 2, check=False,
    )  # fmt: skip
    if site.tool.label != "podman-compose-debian":
        assert done.returncode != 0, done.stdout + done.stderr
    logins = site.container("logins")
    assert site.engine("inspect", "-f", "{{.State.ExitCode}}", logins).strip() == "1"
    said = engine_run(site.tool.engine, "logs", logins)
    for rel in ("secrets/zenoh-users", "secrets/machine.password", "secrets/ui.password"):
        assert f"logins: {rel}: missing" in said.stdout + said.stderr, said
    assert "make them in the project directory: machine credentials init secrets" in said.stderr
    label = f"label=com.docker.compose.project={site.name}"
    running = site.engine("ps", "--filter", label, "--format", "{{.Names}}").split()
    assert running == [], f"{site.tool.label}: {running} run without their logins"
