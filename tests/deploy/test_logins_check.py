"""The logins check before the stack starts (issue 57, reproduction 5: `rm -rf secrets;
podman-compose up -d` exited 0 with nothing running on Debian's podman-compose 1.0.3).

compose.yaml's one-shot `logins` service runs docker/check_logins.py over the project
directory, mounted as a whole (a mount that cannot fail), and every other service waits for it
to finish with 0. Here: the files as written (each stack's check names exactly the login files
its services mount, the command that makes them parses, nothing starts before the check), and
the program as a real process — as root and, where this test may switch users, as the
containers' uid/gid 10001 — against project directories with the files missing, empty,
unreadable or present. What each compose tool makes of it is in test_compose_readers.py, what
an engine does in test_container.py.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from ride_machine.service.adapters.credentials import identities, init_credentials
from tests.deploy import spec
from tests.deploy.compose_tools import (
    IMAGE,
    TOOL_TIMEOUT_S,
    Reader,
    docker_config,
    given_command,
    is_debian_podman_compose,
    podman_up,
    python_bin,
)
from tests.procs import REPO

UID = 10001
CHECK = REPO / "docker" / "check_logins.py"
SITE = "/site"
OVERRIDES = {
    "compose.yaml": None,
    "router": spec.ROUTER_OVERRIDE,
    "gateway": REPO / "docker" / "compose.gateway.yaml",
    "plant": spec.PLANT_OVERRIDE,
    "revpi": spec.REVPI_OVERRIDE,
}
ENV = {"PICONTROL_GID": "996"}  # docker/compose.revpi.yaml asks for it
RUN_TIMEOUT_S = 30.0
SYSTEM_PYTHON = "/usr/bin/python3"


def stack(label: str) -> dict[str, Any]:
    base = spec.load_compose(env=ENV)
    path = OVERRIDES[label]
    return base if path is None else spec.merged(base, spec.load_compose(path, ENV))


def needed(compose: dict[str, Any]) -> set[str]:
    """Every login file a service of `compose` mounts (a secret or a file under secrets/),
    relative to the project directory."""
    files = set()
    declared = compose.get("secrets") or {}
    for name, svc in compose["services"].items():
        if name == "logins":
            continue
        for secret in svc.get("secrets") or []:
            files.add(os.path.normpath(declared[secret]["file"]))
        files |= {
            os.path.normpath(m.source)
            for m in spec.mounts(svc)
            if m.is_bind and m.source.startswith("./secrets/")
        }
    return files


def checked(compose: dict[str, Any]) -> dict[str, list[str]]:
    """Part → the files the logins service's environment names for it."""
    env = spec.environment(spec.service(compose, "logins"))
    return {
        k.removeprefix("LOGIN_FILES_"): v.split()
        for k, v in env.items()
        if k.startswith("LOGIN_FILES_")
    }


@pytest.mark.parametrize("label", sorted(OVERRIDES))
def test_the_check_names_every_login_file_the_stack_mounts(label: str) -> None:
    compose = stack(label)
    parts = checked(compose)
    assert {f for files in parts.values() for f in files} == needed(compose), label
    env = spec.environment(spec.service(compose, "logins"))
    for part in parts:
        assert env.get(f"LOGIN_MAKE_{part}"), f"{label}: no command makes the {part} files"


@pytest.mark.parametrize("label", sorted(OVERRIDES))
def test_nothing_starts_before_the_check_has_passed(label: str) -> None:
    compose = stack(label)
    for name, svc in compose["services"].items():
        if name != "logins":
            deps = spec.depends_on(svc)
            assert deps.get("logins") == "service_completed_successfully", f"{label}: {name}"


def test_the_check_mounts_the_project_directory_and_no_file_that_may_be_missing() -> None:
    """A missing bind source refuses the container (and podman-compose 1.0.3 ignores that):
    the check mounts the directory compose.yaml is in, read-only, and no secret."""
    svc = spec.service(spec.load_compose(), "logins")
    assert [(m.source, m.target, m.read_only) for m in spec.mounts(svc)] == [("./", SITE, True)]
    assert not svc.get("secrets")
    argv = spec.command(svc)
    assert argv[0] == "python" and argv[1:] == [f"{SITE}/docker/check_logins.py", SITE]
    assert (REPO / argv[1].removeprefix(f"{SITE}/")).is_file()
    assert svc["restart"] == "no"  # one run per `up`
    # the command that makes compose.yaml's logins is the package's own
    make = spec.environment(svc)["LOGIN_MAKE_STACK"]
    args = spec.parse_cli(shlex.split(make))
    assert args.cmd == "credentials" and str(args.directory) == "secrets"


def run_check(
    project: Path, env: dict[str, str], *, as_uid: int | None = None
) -> subprocess.CompletedProcess[str]:
    """The check as a real process, as the service runs it: the program from the project
    directory (/site mapped to `project`), the system's python where it runs as uid 10001
    (this venv's lies in a directory closed to that user)."""
    program = project / "docker" / CHECK.name
    program.parent.mkdir(exist_ok=True)
    shutil.copy2(CHECK, program)
    python, kwargs = sys.executable, {}
    if as_uid is not None:
        python, kwargs = SYSTEM_PYTHON, {"user": as_uid, "group": as_uid}
    return subprocess.run(
        [python, str(program), str(project)], capture_output=True, text=True,
        timeout=RUN_TIMEOUT_S, check=False, env={"PATH": os.environ["PATH"], **env}, **kwargs,
    )  # fmt: skip


def logins_env(label: str) -> dict[str, str]:
    return spec.environment(spec.service(stack(label), "logins"))


@pytest.fixture
def open_dir() -> Iterator[Path]:
    """A project directory any user may enter (a pytest tmp_path is closed to uid 10001)."""
    root = Path(tempfile.mkdtemp(prefix="logins-"))
    root.chmod(0o755)
    try:
        yield root
    finally:
        shutil.rmtree(root)


def make_logins(project: Path, mode: int = 0o640, directory_mode: int = 0o710) -> None:
    """As docs/deploy.md says: the logins, then readable by the containers' group."""
    init_credentials(project / "secrets", (*identities(), "router"))
    for name in ("router.crt", "router.key", "site-ca.crt"):  # docker/site-certs.sh's
        (project / "secrets" / name).write_text("x\n")
    for name in ("opcua-users", "gateway-opcua.der", "gateway-opcua.key.pem"):
        (project / "secrets" / name).write_text("x\n")
    for path in [project / "secrets", *(project / "secrets").iterdir()]:
        if os.geteuid() == 0:
            os.chown(path, -1, UID)
        path.chmod(directory_mode if path.is_dir() else mode)


@pytest.mark.parametrize("label", ["compose.yaml", "router", "gateway"])
def test_without_the_logins_it_names_each_file_and_the_command_and_exits_1(
    label: str, open_dir: Path
) -> None:
    env = logins_env(label)
    done = run_check(open_dir, env)
    assert done.returncode == 1, done.stdout + done.stderr
    for files in checked(stack(label)).values():
        for rel in files:
            assert f"logins: {rel}: missing" in done.stderr, done.stderr
    for key, make in env.items():
        if key.startswith("LOGIN_MAKE_"):
            assert f"make them in the project directory: {make}" in done.stderr
    # paths as the operator has them on the host, never the container's
    assert f"{SITE}/" not in done.stderr and str(open_dir) not in done.stderr


def test_with_the_logins_it_passes(open_dir: Path) -> None:
    make_logins(open_dir)
    env = {**logins_env("router"), **logins_env("gateway")}
    done = run_check(open_dir, env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "logins: 11 login files present and readable"


def test_an_empty_or_missing_file_among_the_others_is_named_alone(open_dir: Path) -> None:
    make_logins(open_dir)
    (open_dir / "secrets" / "ui.password").write_text("")
    (open_dir / "secrets" / "zenoh-users").unlink()
    done = run_check(open_dir, logins_env("compose.yaml"))
    assert done.returncode == 1
    named = [line for line in done.stderr.splitlines() if line.startswith("logins: secrets/")]
    assert named == ["logins: secrets/zenoh-users: missing", "logins: secrets/ui.password: empty"]


def test_a_check_without_files_is_a_usage_error(open_dir: Path) -> None:
    assert run_check(open_dir, {}).returncode == 2


needs_root = pytest.mark.skipif(
    os.geteuid() != 0 or not os.access(SYSTEM_PYTHON, os.X_OK),
    reason="running as uid 10001 needs root and a system python3 (/usr/bin/python3)",
)


@needs_root
def test_as_the_containers_user_a_file_it_cannot_read_fails_the_check(open_dir: Path) -> None:
    """The machine would start and fail to read its password: the check says so first."""
    make_logins(open_dir)
    (open_dir / "secrets" / "machine.password").chmod(0o600)  # the chgrp step forgotten
    done = run_check(open_dir, logins_env("compose.yaml"), as_uid=UID)
    assert done.returncode == 1
    assert "logins: secrets/machine.password: not readable by uid/gid 10001" in done.stderr
    assert "chgrp 10001 secrets secrets/* && chmod 0640 secrets/*" in done.stderr


@needs_root
def test_as_the_containers_user_a_closed_directory_is_left_to_the_engine(
    open_dir: Path,
) -> None:
    """A secrets directory closed to uid 10001 (0700, as `machine credentials init` makes it):
    the engine mounts each file itself; the check cannot look, says so, and passes."""
    make_logins(open_dir, directory_mode=0o700)
    done = run_check(open_dir, logins_env("compose.yaml"), as_uid=UID)
    assert done.returncode == 0, done.stderr
    assert "3 files not checked" in done.stdout and "chmod 0710 secrets" in done.stdout
    (open_dir / "secrets").chmod(0o710)  # docs/deploy.md's step: searched, not listed
    done = run_check(open_dir, logins_env("compose.yaml"), as_uid=UID)
    assert done.stdout.strip() == "logins: 3 login files present and readable"


# ------------------------------------------------------- as each compose tool hands it on
def recorded_runs(root: Path) -> list[list[str]]:
    """Every `podman run`/`create` the stand-in was given, refused ones too."""
    lines = (root.parent / "podman.jsonl").read_text().splitlines()
    return [args for args in map(json.loads, lines) if args and args[0] in ("run", "create")]


def flag_values(args: list[str], *flags: str) -> list[str]:
    return [args[i + 1] for i, a in enumerate(args[:-1]) if a in flags]


def login_check(reader: Reader, root: Path, *files: str) -> tuple[list[str], str, dict[str, str]]:
    """(argv, host directory mounted at /site, environment) of the service that mounts the
    project directory, as the tool hands it to its engine."""
    if reader.kind == "podman-compose":
        for args in recorded_runs(root):
            sources = [v.rsplit(":", 2) for v in flag_values(args, "-v", "--volume")]
            site = [src for src, target, *_ in sources if target == "/site"]
            if site:
                env = dict(e.split("=", 1) for e in flag_values(args, "-e", "--env"))
                return args[args.index(IMAGE) + 1 :], site[0], env
    else:
        for svc in docker_config(reader, root, *files).values():
            mounts = [v.split(":") for v in svc.get("volumes") or [] if isinstance(v, str)]  # type: ignore[attr-defined]
            site = [src for src, target, *_ in mounts if target == "/site"]
            if site:
                env = {str(k): str(v) for k, v in svc["environment"].items()}  # type: ignore[attr-defined]
                return given_command(svc["command"]), site[0], env
    raise AssertionError(f"{reader.label}: no service checks the logins (mounts the project)")


def test_without_the_login_files_compose_stops_or_a_service_exits_with_one(
    reader: Reader, project: Path
) -> None:
    """Issue 57, reproduction 5 (`rm -rf secrets; podman-compose up -d`): podman-compose 1.6
    waited for the machine for ever; Debian's 1.0.3 exits 0 whatever its engine says. Now the
    `logins` service, which every tool creates (it mounts only the project directory), exits 1
    naming each missing file, and 1.6 also exits non-zero at once. docker's compose tools read
    the file here (`config`); their `up` stops on the check (test_container.py)."""
    shutil.rmtree(project / "secrets")
    files = ("compose.yaml", "docker/compose.gateway.yaml")
    if reader.kind == "podman-compose":
        try:
            done = podman_up(reader, project, *files)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{reader.label}: up -d still running after {TOOL_TIMEOUT_S:g} s")
        if not is_debian_podman_compose(reader):  # 1.0.3 ignores every podman error
            assert done.returncode != 0, done.stdout + done.stderr
    argv, site, env = login_check(reader, project, *files)
    assert Path(site).resolve() == project.resolve()
    bin_dir = python_bin(project)
    check = subprocess.run(
        [a.replace("/site", site) for a in argv], capture_output=True, text=True, timeout=30,
        check=False, env={"PATH": f"{bin_dir}:{os.environ['PATH']}", **env},
    )  # fmt: skip
    assert check.returncode == 1, check.stdout + check.stderr
    for rel in ("secrets/zenoh-users", "secrets/ui.password", "secrets/opcua-users"):
        assert f"logins: {rel}: missing" in check.stderr, check.stderr
    assert "machine credentials init secrets" in check.stderr
