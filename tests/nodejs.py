"""Node packages of the tests (tests/js, pinned by its package-lock.json): `npm ci` once, or
the test skips and says why (no npm, or no registry to install from)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tests.procs import REPO

JS = REPO / "tests" / "js"


def node_module(name: str) -> Path:
    """The folder of the installed package `name` (e.g. `ajv`, `axe-core`)."""
    path = JS / "node_modules" / name
    if path.is_dir():
        return path
    if shutil.which("npm") is None:
        pytest.skip(f"npm is needed for {name} (tests/js): apt-get install -y npm")
    done = subprocess.run(
        ["npm", "ci", "--no-audit", "--no-fund"],
        cwd=JS,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    if done.returncode != 0 or not path.is_dir():
        pytest.skip(f"npm ci failed (offline registry?): {done.stderr.strip()[-300:]}")
    return path
