"""compose.yaml as each compose implementation on this host hands it to its engine, no engine
needed (tests/deploy/compose_tools.py: a stand-in `podman` for podman-compose 1.0.3 and 1.6,
docker-compose's `config`).

For each, the healthcheck the engine would run (podman: a JSON array is exec form, any other
string is `/bin/sh -c STRING`; docker: `CMD` exec form, `CMD-SHELL` via `/bin/sh -c`) is run
here against a fresh heartbeat file and a stand-in of the UI's endpoint, container paths mapped
to this test's; every implementation starts exactly the logins check, the machine and the rider
by default; an override file's machine command replaces compose.yaml's; the router file merges
as written (its machine keeps compose.yaml's variables and mounts); the hardening is handed on.
Without the login files: test_logins_check.py. Each implementation not installed is skipped,
with the reason."""

from __future__ import annotations

import contextlib
import functools
import http.server
import json
import os
import shutil
import socket
import subprocess
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from ride_machine.sim.plant import SOCKET as PLANT_SOCKET
from tests.deploy import spec
from tests.deploy.compose_tools import (
    IMAGE,
    OVERRIDES,
    Reader,
    docker_config,
    given_command,
    is_debian_podman_compose,
    podman_runs,
    python_bin,
)

HEARTBEAT = "/dev/shm/machine.heartbeat"
UI = "127.0.0.1:8080"


def podman_test(value: str) -> list[str]:
    """What podman 4.3 runs for `--health-cmd VALUE` (checked with `podman create` and
    `podman inspect`): a string that is no JSON array, or an array of one string, is CMD-SHELL
    (`/bin/sh -c`); `["CMD-SHELL", s]` too; a longer array is exec form."""
    if not value.startswith("["):
        return ["/bin/sh", "-c", value]
    test = json.loads(value)
    if test[0] == "CMD-SHELL":
        return ["/bin/sh", "-c", test[1]]
    if test[0] == "CMD":
        return test[1:]
    return test if len(test) > 1 else ["/bin/sh", "-c", test[0]]


def podman_health(args: list[str]) -> list[str]:
    for flag in ("--healthcheck-command", "--health-cmd"):
        if flag in args:
            return podman_test(args[args.index(flag) + 1])
    raise AssertionError(f"no healthcheck in {args}")


def docker_health(svc: dict[str, object]) -> list[str]:
    test = svc["healthcheck"]["test"]  # type: ignore[index]
    if isinstance(test, str):
        return ["/bin/sh", "-c", test]
    kind, *rest = test
    return rest if kind == "CMD" else ["/bin/sh", "-c", rest[0]]


def engine_view(reader: Reader, root: Path) -> tuple[set[str], dict[str, list[str]]]:
    """(services started by default, service → healthcheck argv) as the engine gets them."""
    if reader.kind == "podman-compose":
        runs = podman_runs(reader, root, "compose.yaml")
        checks = {name: podman_health(args) for name, args in runs.items() if name != "logins"}
        return set(runs), checks
    services = docker_config(reader, root, "compose.yaml")
    started = {n for n, s in services.items() if not s.get("profiles")}
    checks = {name: docker_health(svc) for name, svc in services.items() if name != "logins"}
    return started, checks


@contextlib.contextmanager
def serving(directory: Path) -> Iterator[int]:
    """A threaded HTTP server of the files in `directory` on a free loopback port; its port."""
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=directory)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()


@contextlib.contextmanager
def ui_stand_in(root: Path) -> Iterator[int]:
    """An HTTP server answering /api/config as the UI does (200), on a free port."""
    (root / "www" / "api").mkdir(parents=True)
    (root / "www" / "api" / "config").write_text("{}")
    with serving(root / "www") as port:
        yield port


def run_here(argv: list[str], mapping: dict[str, str], path: Path) -> int:
    """A healthcheck argv with container paths and addresses mapped, `python` this one."""
    mapped = []
    for arg in argv:
        for container, host in mapping.items():
            arg = arg.replace(container, host)  # noqa: PLW2901 - each mapping in turn
        mapped.append(arg)
    env = {**os.environ, "PATH": f"{path}:{os.environ['PATH']}"}
    return subprocess.run(mapped, capture_output=True, timeout=30, env=env, check=False).returncode


def test_every_compose_implementation_passes_the_healthchecks_on_intact(
    reader: Reader, project: Path
) -> None:
    started, checks = engine_view(reader, project)
    # the logins check first (it exits), then the machine and the rider
    assert started == {"logins", "machine", "rider"}, f"{reader.label} starts {started}"
    bin_dir = python_bin(project)
    heartbeat = project.parent / "machine.heartbeat"
    heartbeat.touch()
    with ui_stand_in(project) as port:
        mapping = {HEARTBEAT: str(heartbeat), UI: f"127.0.0.1:{port}"}
        assert run_here(checks["machine"], mapping, bin_dir) == 0, checks["machine"]
        assert run_here(checks["rider"], mapping, bin_dir) == 0, checks["rider"]
    heartbeat.unlink()
    assert run_here(checks["machine"], mapping, bin_dir) != 0


@pytest.mark.parametrize("override", OVERRIDES)
def test_every_compose_implementation_replaces_the_machines_command_with_the_overrides(
    reader: Reader, project: Path, override: str
) -> None:
    """Each override's machine command as written, nothing of compose.yaml's before it
    (podman-compose 1.0.3 appends one list to another: the commands are strings)."""
    files = ("compose.yaml", f"docker/{override}")
    written = yaml.safe_load((project / files[1]).read_text())["services"]["machine"]["command"]
    if reader.kind == "podman-compose":
        args = podman_runs(reader, project, *files)["machine"]
        assert args[args.index(IMAGE) + 1 :] == given_command(written), args
    else:
        machine = docker_config(reader, project, *files)["machine"]
        assert given_command(machine["command"]) == given_command(written)


def test_every_compose_implementation_merges_the_router_file_as_written(
    reader: Reader, project: Path
) -> None:
    """The router's command as written; the machine's login variables and mounts kept beside
    the router file's (merged by name and by target)."""
    files = ("compose.yaml", "docker/compose.router.yaml")
    written = yaml.safe_load((project / files[1]).read_text())["services"]["router"]["command"]
    profile = str(project / "zenoh" / "acl.json5")
    if reader.kind == "podman-compose":
        runs = podman_runs(reader, project, *files)
        assert runs["router"][runs["router"].index(IMAGE) + 1 :] == written
        machine = runs["machine"]
        mounts = [a for i, a in enumerate(machine) if machine[i - 1] in ("-v", "--volume")]
        env = [a for i, a in enumerate(machine) if machine[i - 1] in ("-e", "--env")]
        assert "MACHINE_ZENOH_USER=machine" in env, env
        assert any(e.startswith("MACHINE_ZENOH_TLS_ROOT_CA=") for e in env), env
        assert any(m.startswith(f"{profile}:") for m in mounts), mounts
        assert any(m.endswith(":/etc/machine/site-ca.crt:ro") for m in mounts), mounts
        return
    services = docker_config(reader, project, *files)
    assert given_command(services["router"]["command"]) == written
    machine = services["machine"]
    env = machine["environment"]
    assert env["MACHINE_ZENOH_USER"] == "machine" and "MACHINE_ZENOH_TLS_ROOT_CA" in env  # type: ignore[index,operator]
    volumes = machine["volumes"]
    targets = {v["target"] if isinstance(v, dict) else v.split(":")[1] for v in volumes}  # type: ignore[attr-defined]
    assert {"/etc/machine/zenoh.json5", "/etc/machine/site-ca.crt", "/var/lib/machine"} <= targets


HARDENING_FILES = (
    "compose.yaml", "docker/compose.plant.yaml", "docker/compose.router.yaml",
    "docker/compose.gateway.yaml",
)  # fmt: skip


def podman_hardening(args: list[str]) -> dict[str, object]:
    """The hardening a `podman run` argv asks for (None where it asks for none)."""

    def value(*flags: str) -> str | None:
        return next((args[i + 1] for i, a in enumerate(args[:-1]) if a in flags), None)

    return {
        "read_only": "--read-only" in args,
        "tmpfs": value("--tmpfs"),
        "cap_drop": value("--cap-drop"),
        "security_opt": value("--security-opt"),
        "pids_limit": value("--pids-limit"),
        "mem_limit": value("-m", "--memory"),
    }


def test_every_compose_implementation_passes_the_hardening_on(
    reader: Reader, project: Path
) -> None:
    """Issue 57, point 3, as each tool hands it to its engine. Debian's podman-compose 1.0.3
    drops `pids_limit` (it knows no such key): podman's own bound applies (docs/deploy.md)."""
    written = spec.merged(spec.load_compose(project / "compose.yaml"), {})
    for name in HARDENING_FILES[1:]:
        written = spec.merged(written, spec.load_compose(project / name))
    if reader.kind == "podman-compose":
        runs = podman_runs(reader, project, *HARDENING_FILES)
        got = {name: podman_hardening(args) for name, args in runs.items()}
    else:
        config = docker_config(reader, project, *HARDENING_FILES)
        got = {n: {k: svc.get(k) for k in ("read_only", "tmpfs", "cap_drop", "security_opt",
               "pids_limit", "mem_limit")} for n, svc in config.items()}  # fmt: skip
    assert set(got) == set(written["services"])
    for name, svc in written["services"].items():
        want = {
            "read_only": True, "tmpfs": "/tmp", "cap_drop": "ALL",
            "security_opt": "no-new-privileges:true", "pids_limit": str(svc["pids_limit"]),
            "mem_limit": str(svc["mem_limit"]),
        }  # fmt: skip
        if reader.kind == "podman-compose" and is_debian_podman_compose(reader):
            want["pids_limit"] = None
        have = {k: _one(v) for k, v in got[name].items()}
        assert have == want, f"{reader.label}: {name}"


def _one(value: object) -> object:
    """A compose config's list of one (`[ALL]`), or its number, as podman's argument."""
    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    return str(value) if isinstance(value, int) and not isinstance(value, bool) else value


def service_health(reader: Reader, project: Path, override: str, service: str) -> list[str]:
    """The healthcheck argv the engine gets for `service` of compose.yaml + `override`."""
    files = ("compose.yaml", override)
    if reader.kind == "podman-compose":
        return podman_health(podman_runs(reader, project, *files)[service])
    return docker_health(docker_config(reader, project, *files)[service])


def test_every_compose_implementation_gives_the_plant_its_own_healthcheck(
    reader: Reader, project: Path
) -> None:
    """The plant's container ran the image's check, the daemon's heartbeat file, which it has
    not: never healthy. Its own check connects to its control socket (a stand-in here)."""
    check = service_health(reader, project, "docker/compose.plant.yaml", "plant")
    bin_dir = python_bin(project)
    directory = Path(tempfile.mkdtemp(prefix="plant-"))  # short: a socket path is 107 bytes
    try:
        mapping = {"/run/plant": str(directory)}
        assert run_here(check, mapping, bin_dir) != 0  # nothing listens: unhealthy
        with socket.socket(socket.AF_UNIX) as server:
            server.bind(str(directory / PLANT_SOCKET))
            server.listen(1)
            assert run_here(check, mapping, bin_dir) == 0, check
    finally:
        shutil.rmtree(directory)


@contextlib.contextmanager
def metrics_stand_in(root: Path) -> Iterator[int]:
    """An HTTP server answering /metrics (200) as the gateway does, on a free port."""
    (root / "metrics-www").mkdir()
    (root / "metrics-www" / "metrics").write_text("up 1\n")
    with serving(root / "metrics-www") as port:
        yield port


def test_every_compose_implementation_passes_the_gateway_healthcheck_on_intact(
    reader: Reader, project: Path
) -> None:
    check = service_health(reader, project, "docker/compose.gateway.yaml", "gateway")
    bin_dir = python_bin(project)
    with metrics_stand_in(project) as port:
        mapping = {"127.0.0.1:9464": f"127.0.0.1:{port}"}
        assert run_here(check, mapping, bin_dir) == 0, check
    assert run_here(check, mapping, bin_dir) != 0  # nothing answers: unhealthy
