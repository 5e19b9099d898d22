"""`make test` offline once installed (issue 57, reproduction 6): the Makefile's install steps run
only when their lock changed.

Round three ran `npm ci` on every `make test`: npm ci deletes node_modules and installs again
from the registry, so offline, with everything installed, `make test` waited on the network
for minutes. Here the Makefile's own `js` target runs in a scratch tree with a recording
stand-in `npm` first on PATH.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.procs import REPO

LOCKS = ("tests/js/package-lock.json", "tests/gateway/js/package-lock.json")
FAKE_NPM = """#!{python}
import json, os, sys
args = sys.argv[1:]
with open(os.environ["FAKE_NPM_LOG"], "a") as log:
    log.write(json.dumps(args) + "\\n")
prefix = args[args.index("--prefix") + 1]
os.makedirs(os.path.join(prefix, "node_modules"), exist_ok=True)
with open(os.path.join(prefix, "node_modules", ".package-lock.json"), "w") as f:
    f.write("{{}}")
"""


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    root = tmp_path / "tree"
    for lock in LOCKS:
        (root / lock).parent.mkdir(parents=True)
        shutil.copy2(REPO / lock, root / lock)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    npm = bin_dir / "npm"
    npm.write_text(FAKE_NPM.format(python=sys.executable))
    npm.chmod(0o755)
    return root


def make_js(root: Path, with_npm: bool = True) -> tuple[list[list[str]], str]:
    """`make js` in `root` with the repository's Makefile; the npm calls it made, its output."""
    log = root.parent / "npm.jsonl"
    log.unlink(missing_ok=True)
    # without npm: a PATH of make and the shell's tools only
    bin_dir = root.parent / ("bin" if with_npm else "no-npm")
    path = f"{bin_dir}:{os.environ['PATH']}" if with_npm else str(bin_dir)
    env = {**os.environ, "PATH": path, "FAKE_NPM_LOG": str(log)}
    done = subprocess.run(
        ["make", "--no-print-directory", "-f", str(REPO / "Makefile"), "js"],
        cwd=root, capture_output=True, text=True, timeout=60, env=env, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    calls = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    return calls, done.stdout + done.stderr


def prefixes(calls: list[list[str]]) -> list[str]:
    assert all(c[0] == "ci" for c in calls), calls
    return sorted(c[c.index("--prefix") + 1] for c in calls)


def test_npm_ci_runs_once_per_lock_and_again_only_when_the_lock_changes(tree: Path) -> None:
    calls, _ = make_js(tree)
    assert prefixes(calls) == ["tests/gateway/js", "tests/js"]  # a fresh clone installs both
    calls, _ = make_js(tree)
    assert calls == [], "installed and unchanged: no npm (offline it would wait on the registry)"
    later = time.time() + 10
    os.utime(tree / LOCKS[0], (later, later))  # a pull that changed one lock
    calls, _ = make_js(tree)
    assert prefixes(calls) == ["tests/js"]


def test_without_npm_make_js_says_the_checks_are_skipped(tree: Path) -> None:
    bare = tree.parent / "no-npm"
    bare.mkdir()
    for tool in ("make", "sh", "touch"):
        found = shutil.which(tool)
        assert found is not None, tool
        (bare / tool).symlink_to(found)
    calls, output = make_js(tree, with_npm=False)
    assert calls == []
    assert "npm not installed" in output
