"""Fixtures of the deployment tests: each compose implementation installed, a project
directory made as docs/deploy.md says (tests/deploy/compose_tools.py), and the image built once
per run for the tests that run it (tests/deploy/engines.py)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.deploy.compose_tools import READERS, Reader, make_project
from tests.deploy.engines import (
    BUILD_TIMEOUT_S,
    ENGINE,
    IMAGE,
    build_args,
    build_context,
    engine,
    skip_reason,
)


@pytest.fixture(params=READERS or [None], ids=lambda r: r.label if r else "none")
def reader(request: pytest.FixtureRequest) -> Reader:
    """Each compose implementation installed; the test skips when there is none."""
    if request.param is None:
        pytest.skip("no compose implementation (podman-compose, docker-compose) installed")
    found: Reader = request.param
    return found


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """compose.yaml's files in a project directory, with the logins made as the docs say."""
    return make_project(tmp_path)


@pytest.fixture(scope="session")
def context(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_context(tmp_path_factory.mktemp("build"))


@pytest.fixture(scope="session")
def image(context: Path) -> str:
    reason = skip_reason()
    if reason:
        pytest.skip(reason)
    replaced = engine("images", "-q", "--no-trunc", IMAGE).strip()
    # As docs/deploy.md builds (no builder stage left behind: reproduction 7 of issue 57).
    done = subprocess.run(
        [str(ENGINE), "build", "--format", "docker", "--layers=false", "-t", IMAGE,
         *build_args(), str(context)],
        capture_output=True, text=True, timeout=BUILD_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    # issue 41: no "missing build argument" and no useradd SYS_UID_MAX warning on a build
    assert "missing" not in done.stderr and "SYS_UID_MAX" not in done.stdout + done.stderr
    if replaced and replaced != engine("images", "-q", "--no-trunc", IMAGE).strip():
        engine("rmi", replaced, check=False)  # the last run's, now unnamed (unless in use)
    return IMAGE
