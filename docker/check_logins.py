"""The stack's logins, checked before anything else starts (compose.yaml's `logins` service).

    python /site/docker/check_logins.py /site

`/site` is the project directory (where compose.yaml is), mounted read-only: the directory
itself, so the mount cannot fail when the login files are missing (a missing file mounted on
its own refuses the container, and Debian's podman-compose 1.0.3 ignores that and exits 0).

Which files: every environment variable `LOGIN_FILES_<PART>` (paths relative to the project
directory, spaces between them), each with `LOGIN_MAKE_<PART>`, the command that makes them.
compose.yaml names its own; an override file adds its part (environment merges by name in
every compose tool). Each file must exist, be a non-empty regular file and be readable by
this container's user, uid/gid 10001, as the services that mount it read it. Behind a
directory closed to that user (0700, as `machine credentials init` makes it) a file cannot be
looked at: that is said, not failed (the engine checks each file as it mounts it).

Exit 0 when all are there; 1 with each file's problem and the command that fixes it, in the
project directory's terms (valid on the host); 2 on a usage error. The other services depend
on this one finishing with 0 (`condition: service_completed_successfully`; docker's compose
tools wait for that, podman-compose does not: docs/deploy.md, "The logins check").
"""

from __future__ import annotations

import os
import stat
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

FILES_PREFIX = "LOGIN_FILES_"
MAKE_PREFIX = "LOGIN_MAKE_"
EXIT_OK, EXIT_MISSING, EXIT_USAGE = 0, 1, 2
READABLE = "chgrp 10001 secrets secrets/* && chmod 0640 secrets/* && chmod 0710 secrets"
"""What makes the files readable by the containers' user (docs/deploy.md, "Credentials")."""
OPEN = "chgrp 10001 secrets && chmod 0710 secrets"
"""What lets this check look into the directory (search, not list) as the services do."""


@dataclass(frozen=True)
class Part:
    """One compose file's logins: the files, and the command that makes them."""

    name: str
    files: tuple[str, ...]
    make: str


def parts(env: Mapping[str, str]) -> list[Part]:
    """The login files the environment names, by part, in name order."""
    found = []
    for key in sorted(env):
        if key.startswith(FILES_PREFIX) and env[key].split():
            name = key.removeprefix(FILES_PREFIX)
            make = env.get(MAKE_PREFIX + name, "").strip() or "see docs/deploy.md, Credentials"
            found.append(Part(name, tuple(env[key].split()), make))
    return found


UNCHECKED = "unchecked"
"""A file behind a directory closed to uid/gid 10001: not a failure, the engine checks it as
it mounts it, but this check cannot (docs/deploy.md: `chmod 0710 secrets` opens it)."""


def problem(root: Path, rel: str) -> str | None:
    """Why `rel` (under `root`) cannot serve as a login file, UNCHECKED, or None."""
    path = root / rel
    try:
        info = path.stat()
    except FileNotFoundError:
        return "missing"
    except PermissionError:
        return UNCHECKED
    if not stat.S_ISREG(info.st_mode):
        return "not a regular file"
    if info.st_size == 0:
        return "empty"
    try:
        os.close(os.open(path, os.O_RDONLY))
    except PermissionError:
        return "not readable by uid/gid 10001"
    return None


def check(root: Path, env: Mapping[str, str]) -> tuple[int, list[str]]:
    """(exit code, the lines to print)."""
    found = parts(env)
    if not found:
        return EXIT_USAGE, [f"logins: no {FILES_PREFIX}* variable names a file to check"]
    lines: list[str] = []
    unchecked: list[str] = []
    for part in found:
        seen = [(rel, problem(root, rel)) for rel in part.files]
        unchecked += [rel for rel, why in seen if why == UNCHECKED]
        bad = [(rel, why) for rel, why in seen if why not in (None, UNCHECKED)]
        lines += [f"logins: {rel}: {why}" for rel, why in bad]
        if any(why in ("missing", "empty") for _, why in bad):
            lines.append(f"logins:   make them in the project directory: {part.make}")
    note = [
        f"logins: {len(unchecked)} files not checked: their directory is closed to uid/gid"
        f" 10001 (the engine checks each as it mounts it; `{OPEN}` lets this check see them)"
    ] if unchecked else []  # fmt: skip
    if not lines:
        count = sum(len(p.files) for p in found) - len(unchecked)
        fine = [f"logins: {count} login files present and readable"] if count else []
        return EXIT_OK, [*fine, *note]
    lines.append(f"logins:   then let the containers read them: {READABLE}")
    lines.append(
        "logins: then `up` again (paths are relative to the project directory, where"
        " compose.yaml is; docs/deploy.md, The logins check)"
    )
    return EXIT_MISSING, [*lines, *note]


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: check_logins.py PROJECT_DIR", file=sys.stderr)
        return EXIT_USAGE
    code, lines = check(Path(argv[0]), os.environ)
    print("\n".join(lines), file=sys.stderr if code else sys.stdout, flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
