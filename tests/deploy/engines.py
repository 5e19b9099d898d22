"""The container engines on this host, for the tests that run the image (test_container.py,
test_compose_engines.py, test_arm64.py): podman, and Debian's docker 20.10 where its dockerd runs;
the build context as .dockerignore makes it, with pip's CA where this host has one."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from tests.deploy import dockerignore
from tests.procs import REPO

ENGINE = shutil.which("podman")
DOCKER = "/usr/bin/docker" if Path("/usr/bin/docker").exists() else shutil.which("docker")
BASE_IMAGE = "docker.io/library/python:3.11-slim"
IMAGE = "localhost/ride-machine:0.1.0"
BUILD_TIMEOUT_S = 300.0
STEP_TIMEOUT_S = 60.0
HEALTHY_TIMEOUT_S = 30.0
UID = 10001
Done = subprocess.CompletedProcess[str]


def engine(*args: str, timeout: float = STEP_TIMEOUT_S, check: bool = True) -> str:
    assert ENGINE is not None
    return run_engine("podman", *args, timeout=timeout, check=check)


def skip_reason() -> str | None:
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


def engine_run(engine: str, *args: str, timeout: float = STEP_TIMEOUT_S) -> Done:
    binary = str(ENGINE if engine == "podman" else DOCKER)
    return subprocess.run(
        [binary, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def run_engine(engine: str, *args: str, timeout: float = STEP_TIMEOUT_S, check: bool = True) -> str:
    done = engine_run(engine, *args, timeout=timeout)
    if check and done.returncode != 0:
        raise AssertionError(f"{engine} {' '.join(args)}: exit {done.returncode}\n{done.stderr}")
    return done.stdout


def build_context(tmp: Path) -> Path:
    """The files the build context holds (.dockerignore), copied, plus pip's CA if this host
    has one (docker/pip/ca.crt: pip in the build goes through the same proxy)."""
    context = tmp / "context"
    for rel in dockerignore.context_files():
        (context / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, context / rel)
    shutil.copy2(REPO / "Dockerfile", context / "Dockerfile")
    ca = os.environ.get("PIP_CERT") or os.environ.get("SSL_CERT_FILE")
    if ca and Path(ca).is_file():
        (context / "docker" / "pip").mkdir(parents=True, exist_ok=True)
        shutil.copy2(ca, context / "docker" / "pip" / "ca.crt")
    return context


def build_args() -> list[str]:
    return [
        arg
        for name in ("PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_TRUSTED_HOST")
        if os.environ.get(name)
        for arg in ("--build-arg", f"{name}={os.environ[name]}")
    ]
