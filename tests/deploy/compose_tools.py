"""The compose implementations on this host, and how each hands a compose file to its engine
with no engine: podman-compose (Debian 12's 1.0.3, PyPI's 1.6) against a stand-in `podman` that
records the commands it is given and, like podman, refuses a container whose bind source is
missing; docker-compose 1.29 (and `docker compose` v2 where present) by its resolved file
(`config`). Used by test_compose_readers.py and test_logins_check.py (fixtures in conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

from ride_machine.service.adapters.credentials import identities, init_credentials
from ride_machine.service.adapters.opcua_credentials import opcua_files
from tests.procs import REPO

TOOL_TIMEOUT_S = 60.0
IMAGE = "localhost/ride-machine:0.1.0"
COMPOSE_ENV = {**os.environ, "PICONTROL_GID": "996"}  # docker/compose.revpi.yaml asks for it
OVERRIDES = ("compose.plant.yaml", "compose.revpi.yaml", "compose.router.yaml")
FAKE_PODMAN = """#!{python}
import json, os, sys
args = sys.argv[1:]
log_path = os.environ["FAKE_PODMAN_LOG"]
with open(log_path, "a") as log:
    log.write(json.dumps(args) + "\\n")
made = log_path + ".containers"
names = set(open(made).read().split()) if os.path.exists(made) else set()
if args[:1] in (["--version"], ["-v"]):
    print("podman version 4.3.1")
elif args[:1] == ["version"]:
    print("4.3.1")
elif args[:1] in (["create"], ["run"]):
    # As podman 4.3: a bind source that does not exist refuses the container (exit 125).
    for i, a in enumerate(args[:-1]):
        source = args[i + 1].split(":")[0] if a in ("-v", "--volume") else ""
        if source.startswith(("/", ".")) and not os.path.exists(source):
            sys.exit(print(f"Error: statfs {{source}}: no such file or directory") or 125)
    name = next(a.split("=", 1)[1] for a in args if a.startswith("--name="))
    with open(made, "a") as f:
        f.write(name + "\\n")
elif args[:1] in (["start"], ["wait"]):
    missing = [a for a in args[1:] if not a.startswith("-") and a not in names]
    if missing:
        sys.exit(print(f"Error: no container with name or ID {{missing[0]!r}} found") or 125)
elif "inspect" in args[:2]:
    print('[{{"Id": "0"}}]')
elif "json" in args:
    print("[]")
"""


@dataclass(frozen=True)
class Reader:
    """One compose implementation: how to call it, and which kind it is."""

    label: str
    argv: tuple[str, ...]
    kind: str  # "podman-compose" or "docker"


def _version(argv: list[str]) -> str | None:
    try:
        done = subprocess.run(
            [*argv, "version"], capture_output=True, text=True, timeout=30, check=False
        )
    except OSError:
        return None
    return done.stdout.strip().splitlines()[-1] if done.returncode == 0 and done.stdout else None


def readers() -> list[Reader]:
    found: list[Reader] = []
    podman_composes = {"/usr/bin/podman-compose", str(REPO / ".venv/bin/podman-compose")}
    podman_composes |= {p for p in [shutil.which("podman-compose")] if p}
    for path in sorted(podman_composes):
        if Path(path).exists():
            found.append(Reader(f"podman-compose ({path})", (path,), "podman-compose"))
    if (path := shutil.which("docker-compose")) is not None:
        found.append(Reader(f"docker-compose ({path})", (path,), "docker"))
    docker = shutil.which("docker")
    if docker is not None and _version([docker, "compose"]) is not None:
        found.append(Reader("docker compose (v2)", (docker, "compose"), "docker"))
    return found


def _shebang_python(path: str) -> str:
    """podman-compose's own interpreter (Debian's is /usr/bin/python3, PyPI's the venv's)."""
    first = Path(path).read_text().splitlines()[0]
    return first[2:].strip() if first.startswith("#!") else sys.executable


READERS = readers()


def podman_up(reader: Reader, root: Path, *files: str) -> subprocess.CompletedProcess[str]:
    """podman-compose's `up -d` against the stand-in podman (bounded: a hang fails the test)."""
    fake = root.parent / "fake-bin"
    fake.mkdir(exist_ok=True)
    podman = fake / "podman"
    podman.write_text(FAKE_PODMAN.format(python=sys.executable))
    podman.chmod(0o755)
    log = root.parent / "podman.jsonl"
    log.unlink(missing_ok=True)
    Path(f"{log}.containers").unlink(missing_ok=True)
    python = _shebang_python(reader.argv[-1])
    argv = [python, reader.argv[-1], *(f for name in files for f in ("-f", name))]
    env = {**COMPOSE_ENV, "PATH": f"{fake}:{os.environ['PATH']}", "FAKE_PODMAN_LOG": str(log)}
    return subprocess.run(
        [*argv, "-p", "readers", "up", "-d", "--no-build"],
        cwd=root, capture_output=True, text=True, timeout=TOOL_TIMEOUT_S, env=env, check=False,
    )  # fmt: skip


def podman_runs(reader: Reader, root: Path, *files: str) -> dict[str, list[str]]:
    """Service → the `podman run`/`create` argv podman-compose gives for `up -d`."""
    done = podman_up(reader, root, *files)
    assert done.returncode == 0, done.stdout + done.stderr
    runs = {}
    for line in (root.parent / "podman.jsonl").read_text().splitlines():
        args = json.loads(line)
        if args and args[0] in ("run", "create"):
            label = next(a for a in args if a.startswith("com.docker.compose.service="))
            runs[label.partition("=")[2]] = args
    return runs


def docker_config(reader: Reader, root: Path, *files: str) -> dict[str, dict[str, object]]:
    argv = [*reader.argv, *(f for name in files for f in ("-f", name)), "config"]
    done = subprocess.run(
        argv, cwd=root, capture_output=True, text=True, timeout=TOOL_TIMEOUT_S, check=False,
        env=COMPOSE_ENV,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    services: dict[str, dict[str, object]] = yaml.safe_load(done.stdout)["services"]
    return services


def given_command(value: object) -> list[str]:
    return shlex.split(value) if isinstance(value, str) else [str(a) for a in value]  # type: ignore[attr-defined]


def is_debian_podman_compose(reader: Reader) -> bool:
    """Whether `reader` is podman-compose 1.0.3 (Debian 12's)."""
    version = subprocess.run(
        [_shebang_python(reader.argv[-1]), reader.argv[-1], "version"],
        capture_output=True, text=True, timeout=TOOL_TIMEOUT_S, check=False,
    )  # fmt: skip
    return re.search(r"version\s+1\.0\.3\b", version.stdout) is not None


def python_bin(project: Path) -> Path:
    """A bin/ beside the project whose `python` is this interpreter (the healthchecks run
    `python`)."""
    bin_dir = project.parent / "bin"
    bin_dir.mkdir()
    (bin_dir / "python").symlink_to(sys.executable)
    return bin_dir


def make_project(tmp_path: Path) -> Path:
    """compose.yaml's files in a project directory, with the logins made as the docs say."""
    root = tmp_path / "site"
    for rel in ("compose.yaml", "machine.toml", "zenoh.json5", "zenoh/acl.json5"):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, root / rel)
    for name in ("compose.gateway.yaml", *OVERRIDES, "check_logins.py"):
        (root / "docker").mkdir(exist_ok=True)
        shutil.copy2(REPO / "docker" / name, root / "docker" / name)
    init_credentials(root / "secrets", (*identities(), "router"))
    for path in opcua_files(root / "secrets"):  # the gateway's, made by the same command
        path.write_text("")
    for name in ("site-ca.crt", "router.crt", "router.key"):  # docker/site-certs.sh's files
        (root / "secrets" / name).write_text("")
    return root
