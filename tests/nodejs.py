"""Node packages of the tests (tests/js and tests/gateway/js, each pinned by its
package-lock.json): `npm ci` once, or the test skips and says why (no node or npm, or no
registry to install from)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tests.procs import REPO

JS = REPO / "tests" / "js"


def node_module(name: str, folder: Path = JS, *, node: bool = False) -> Path:
    """The folder of the installed package `name` (e.g. `ajv`, `axe-core`) of `folder`'s
    lock file; `node`: the test also runs node itself."""
    if node and shutil.which("node") is None:
        pytest.skip(f"node is needed to run {name}")
    path = folder / "node_modules" / name
    if path.is_dir():
        return path
    if shutil.which("npm") is None:
        pytest.skip(
            f"npm is needed for {name} ({folder.relative_to(REPO)}): apt-get install -y npm"
        )
    done = subprocess.run(
        ["npm", "ci", "--no-audit", "--no-fund"],
        cwd=folder,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    if done.returncode != 0 or not path.is_dir():
        pytest.skip(f"npm ci failed (offline registry?): {done.stderr.strip()[-300:]}")
    return path
