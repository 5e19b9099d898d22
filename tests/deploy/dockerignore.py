"""The Docker build context as `.dockerignore` makes it: which files the build is sent."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from tests.procs import REPO

DOCKERIGNORE = REPO / ".dockerignore"


def ignore_patterns(path: Path = DOCKERIGNORE) -> list[tuple[bool, re.Pattern[str]]]:
    """(is_exception, regex) per `.dockerignore` line, in order (the last match wins)."""
    out = []
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pattern = line[1:] if negate else line
        out.append((negate, glob_regex(pattern.strip().strip("/"))))
    return out


def glob_regex(pattern: str) -> re.Pattern[str]:
    out = ""
    i = 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out += "(?:.*/)?"
            i += 3
        elif pattern.startswith("**", i):
            out += ".*"
            i += 2
        elif pattern[i] == "*":
            out += "[^/]*"
            i += 1
        elif pattern[i] == "?":
            out += "[^/]"
            i += 1
        else:
            out += re.escape(pattern[i])
            i += 1
    return re.compile(out + r"\Z")


def in_context(rel: str, patterns: Sequence[tuple[bool, re.Pattern[str]]]) -> bool:
    """Whether Docker sends `rel` (relative to the context) to the build: a pattern excludes
    a path when it matches the path or one of its parent directories."""
    parts = rel.strip("/").split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    excluded = False
    for negate, regex in patterns:
        if any(regex.match(p) for p in prefixes):
            excluded = not negate
    return not excluded


def context_files(root: Path = REPO) -> Iterator[str]:
    """Every file of the build context, relative to `root` (version-control data skipped)."""
    patterns = ignore_patterns(root / ".dockerignore")
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = os.path.relpath(dirpath, root)
        dirnames[:] = [d for d in dirnames if d != ".git"]
        for name in filenames:
            rel = name if rel_dir == "." else f"{rel_dir}/{name}"
            if in_context(rel, patterns):
                yield rel


def context_wheel(tmp: Path, timeout: float) -> tuple[list[str], Path]:
    """The build context copied under `tmp` and made into the project's wheel offline, as the
    image's builder stage makes it (`pip wheel`, no index, no build isolation): the context's
    files and the wheel."""
    context, out = tmp / "context", tmp / "wheels"
    files = sorted(context_files())
    for rel in files:
        (context / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, context / rel)
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
         "--wheel-dir", str(out), str(context)],
        capture_output=True, text=True, timeout=timeout, check=False,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout + build.stderr
    (wheel,) = out.glob("ride_machine-*.whl")
    return files, wheel
