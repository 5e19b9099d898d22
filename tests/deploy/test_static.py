"""compose.yaml and its override files checked against the package, the image and the repo.

There is no container engine here, so each deployment file is parsed and every claim it makes
is checked where it can fail: commands go through the package's own argparse parsers, mounted
files must exist, ports and machine ids must agree across files and with the image (the
Dockerfile's own checks are in test_dockerfile.py, the hardening's in test_hardening.py).
"""

from __future__ import annotations

import importlib.metadata
import inspect
import json
import re
import shlex
import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import zenoh

from service.adapters.credentials import DICTIONARY, identities, password_file
from service.adapters.heartbeat import HEARTBEAT_FILE_ENV, INTERVAL_S
from service.adapters.opcua_credentials import opcua_files
from service.bus import close_session
from service.config.model import MachineConfig
from service.supervision.daemon import SHUTDOWN_DEADLINE_S
from tests.deploy import spec
from tests.procs import REPO

UID = 10001
BUILD_TIMEOUT_S = 120.0
LINT_TIMEOUT_S = 60.0
PICONTROL_ENV = {"PICONTROL_GID": "996"}


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return spec.load_compose()


@pytest.fixture(scope="module")
def router() -> dict[str, Any]:
    return spec.load_compose(spec.ROUTER_OVERRIDE)


@pytest.fixture(scope="module")
def docker() -> list[spec.Instruction]:
    return spec.dockerfile()


def zenoh_file(path: Path) -> zenoh.Config:
    return zenoh.Config.from_file(str(path))


def listen_port(path: Path) -> int:
    """The port of the (single) listen endpoint of a zenoh.json5."""
    (endpoint,) = zenoh_file(path).get_json("listen/endpoints").strip("[]").split(",")
    return int(endpoint.strip('"').rsplit(":", 1)[1])


def endpoint_parts(endpoint: str) -> tuple[str, int]:
    proto, _, address = endpoint.partition("/")
    assert proto == "tcp", endpoint
    host, _, port = address.rpartition(":")
    return host, int(port)


def repo_file(mount: spec.Mount) -> Path:
    return (REPO / mount.source).resolve()


def machine_toml_id() -> str:
    config = MachineConfig.model_validate(tomllib.loads((REPO / "machine.toml").read_text()))
    return config.machine.id


# ------------------------------------------------------------------------------ compose
def test_machine_and_rider_run_by_default_and_the_router_only_from_its_own_file(
    compose: dict[str, Any], router: dict[str, Any]
) -> None:
    """No `profiles:` anywhere: podman-compose 1.0.3 ignores them and starts every service."""
    assert set(compose["services"]) == {"machine", "rider"}
    assert set(router["services"]) == {"router"}
    for name, svc in [*compose["services"].items(), *router["services"].items()]:
        assert "profiles" not in svc, name


def test_service_commands_parse_with_the_package_parsers(compose: dict[str, Any]) -> None:
    machine = spec.parse_cli(spec.command(spec.service(compose, "machine")))
    # issue 36: the daemon runs as the supervisor's child
    assert (machine.cmd, machine.hal) == ("supervise", "sim")
    rider = spec.parse_cli(spec.command(spec.service(compose, "rider")))
    assert rider.cmd == "ui"
    assert rider.ui.host == "0.0.0.0"  # reachable through the published port


def test_a_typo_in_a_command_fails_the_parse() -> None:
    with pytest.raises(spec.SpecError, match="unrecognized"):
        spec.parse_cli(["machine", "run", "--sim", "--zenoh-confg", "z.json5"])
    with pytest.raises(spec.SpecError, match="does not parse"):
        spec.parse_cli(["machine", "run", "--hal", "revpy"])
    with pytest.raises(spec.SpecError, match="unrecognized"):
        spec.parse_cli(["rider", "status", "--host", "0.0.0.0"])
    with pytest.raises(spec.SpecError, match="unrecognized"):
        spec.parse_cli(["rider", "ui", "--hots", "0.0.0.0"])
    with pytest.raises(spec.SpecError, match="not an entry point"):
        spec.parse_cli(["machined", "run"])


def test_the_rider_connects_where_the_machine_listens(compose: dict[str, Any]) -> None:
    machine = spec.service(compose, "machine")
    rider = spec.service(compose, "rider")
    port = listen_port(REPO / "zenoh.json5")
    (endpoint,) = spec.parse_cli(spec.command(rider)).connect
    assert endpoint_parts(endpoint) == ("machine", port)
    assert spec.environment(rider)["RIDER_CONNECT"] == endpoint
    assert "machine" in compose["services"]  # the host name is the service name
    machine_listen = listen_port(REPO / "zenoh" / "acl.json5")  # the profile it runs
    assert spec.parse_cli(spec.command(machine)).listen == [] and machine_listen == port


def test_one_machine_id_for_daemon_healthcheck_ui_and_revpi_variant(
    compose: dict[str, Any],
) -> None:
    machine_id = spec.parse_cli(spec.command(spec.service(compose, "machine"))).machine_id
    assert spec.parse_cli(spec.command(spec.service(compose, "rider"))).machine == machine_id
    revpi = spec.load_compose(spec.REVPI_OVERRIDE, PICONTROL_ENV)
    assert spec.parse_cli(spec.command(spec.service(revpi, "machine"))).machine_id == machine_id


def test_mounted_files_exist_and_are_read_only(
    compose: dict[str, Any], router: dict[str, Any]
) -> None:
    for name, svc in [*compose["services"].items(), *router["services"].items()]:
        for m in spec.mounts(svc):
            if m.is_bind:
                assert repo_file(m).is_file(), f"{name}: {m.source} is not a file in the repo"
                assert repo_file(m).is_relative_to(REPO), f"{name}: {m.source} leaves the repo"
                assert m.read_only, f"{name}: {m.source} should be mounted :ro"


def test_machine_runs_the_authenticated_profile_and_clients_log_in(
    compose: dict[str, Any],
) -> None:
    """Issue 15's safe default: the machine asks every peer for a login (zenoh/acl.json5) and
    every client presents one, from files `machine credentials init secrets` makes."""
    sources = {}
    for name in ("machine", "rider"):
        svc = spec.service(compose, name)
        targets = {m.target: m for m in spec.mounts(svc)}
        sources[name] = targets[str(spec.parse_cli(spec.command(svc)).zenoh_config)].source
    assert sources == {"machine": "./zenoh/acl.json5", "rider": "./zenoh.json5"}
    machine = spec.service(compose, "machine")
    env = spec.environment(machine)
    secrets = spec.secret_paths(compose, machine, REPO / "secrets")
    assert secrets[env["MACHINE_ZENOH_DICTIONARY_FILE"]].name == DICTIONARY
    # the supervisor's daemon child logs in to its router as `machine`; the UI as station ui
    assert env["MACHINE_ZENOH_USER"] == "machine"
    machine_password = secrets[env["MACHINE_ZENOH_PASSWORD_FILE"]]
    assert machine_password == password_file(REPO / "secrets", "machine")
    rider = spec.service(compose, "rider")
    env = spec.environment(rider)
    assert env["RIDER_ZENOH_USER"] == "ui"  # the stack's own station, a login of its own
    host = spec.secret_paths(compose, rider, REPO / "secrets")[env["RIDER_ZENOH_PASSWORD_FILE"]]
    assert host == password_file(REPO / "secrets", "ui")
    declared = {Path(d["file"]).name for d in compose["secrets"].values()}
    gateway = {p.name for p in opcua_files(Path())}  # the plant gateway's (docs/plant.md)
    logins = {password_file(Path(), u).name for u in identities()}
    assert declared <= logins | {DICTIONARY} | gateway


def test_machine_config_and_data_dir_are_mounted(compose: dict[str, Any]) -> None:
    svc = spec.service(compose, "machine")
    args = spec.parse_cli(spec.command(svc))
    targets = {m.target: m for m in spec.mounts(svc)}
    assert targets[str(args.config)].source == "./machine.toml"
    data = targets[str(args.data_dir)]
    assert not data.is_bind and not data.read_only
    assert data.source in (compose.get("volumes") or {}), "declare the named volume"


def test_services_restart_and_stop_gracefully(
    compose: dict[str, Any], router: dict[str, Any]
) -> None:
    for name, svc in [*compose["services"].items(), *router["services"].items()]:
        assert svc.get("restart") == "unless-stopped", name
        assert svc.get("stop_signal", "SIGTERM") == "SIGTERM", name
    grace = spec.seconds(spec.service(compose, "machine")["stop_grace_period"])
    # Outputs go safe at once; the grace period must outlast the bounded Zenoh close after it.
    close_bound = inspect.signature(close_session).parameters["timeout"].default
    assert grace >= close_bound + 2.0
    # under the supervisor: the child's own stop deadline, then the supervisor's close
    assert grace >= SHUTDOWN_DEADLINE_S + close_bound


def test_every_service_rotates_its_log(compose: dict[str, Any], router: dict[str, Any]) -> None:
    """An edge box logs to an SD card: json-file with a size cap on every service."""
    for name, svc in [*compose["services"].items(), *router["services"].items()]:
        logging = svc.get("logging") or {}
        assert logging.get("driver") == "json-file", name
        options = logging.get("options") or {}
        assert re.fullmatch(r"\d+[km]", str(options.get("max-size", ""))), name
        assert int(options.get("max-file", 0)) >= 2, name


def test_only_the_ui_and_the_router_are_published(
    compose: dict[str, Any], router: dict[str, Any]
) -> None:
    assert "ports" not in spec.service(compose, "machine")
    rider = spec.service(compose, "rider")
    ui_port = spec.parse_cli(spec.command(rider)).ui.port
    assert rider["ports"] == [f"127.0.0.1:{ui_port}:{ui_port}"]
    router_port = listen_port(REPO / "docker" / "zenohd.json5")
    # the router asks for logins but has no ACL of its own: host loopback only
    assert spec.service(router, "router")["ports"] == [f"127.0.0.1:{router_port}:{router_port}"]


def test_machine_healthcheck_reads_the_heartbeat_file(
    compose: dict[str, Any], docker: list[spec.Instruction]
) -> None:
    """A shell string (CMD-SHELL, which every compose implementation passes on) that looks at
    the age of the file the daemon touches; the same file as the image's ENV and check."""
    svc = spec.service(compose, "machine")
    check = svc["healthcheck"]
    assert check["test"][0] == "CMD-SHELL" and len(check["test"]) == 2
    path = spec.environment(svc)[HEARTBEAT_FILE_ENV]
    assert path == spec.image_env(docker)[HEARTBEAT_FILE_ENV]
    assert path.startswith("/dev/shm/"), "a tmpfs: no write to the SD card every second"
    assert spec.heartbeat_freshness_s(check["test"][1], path) >= 5 * INTERVAL_S
    assert check["retries"] >= 2 and spec.seconds(check["start_period"]) >= 10
    (image_check,) = spec.image_args(docker, "HEALTHCHECK")
    image_argv = spec.exec_form(spec.split_options(image_check)[1].removeprefix("CMD "))
    assert image_argv == ["/bin/sh", "-c", check["test"][1]]


def test_rider_healthcheck_probes_its_own_ui(compose: dict[str, Any]) -> None:
    """The image's healthcheck looks for a daemon on 127.0.0.1: the UI container replaces it."""
    svc = spec.service(compose, "rider")
    assert svc["healthcheck"]["test"][0] == "CMD-SHELL"
    argv = shlex.split(spec.healthcheck_argv(svc)[2])
    assert argv[:2] == ["python", "-c"]
    compile(argv[2], "<healthcheck>", "exec")
    (url,) = re.findall(r"'(http://[^']+)'", argv[2])
    ui = spec.parse_cli(spec.command(svc)).ui
    assert (urlsplit(url).hostname, urlsplit(url).port) == ("127.0.0.1", ui.port)


def test_router_is_the_zenoh_release_we_build_against(router: dict[str, Any]) -> None:
    image = spec.service(router, "router")["image"]
    name, _, tag = image.partition(":")
    assert name == "docker.io/eclipse/zenoh"  # fully qualified: podman resolves no short names
    assert tag == importlib.metadata.version("eclipse-zenoh"), "bump the image with the library"


def test_router_config_connects_to_the_machine_service(
    compose: dict[str, Any], router: dict[str, Any]
) -> None:
    svc = spec.service(router, "router")
    # A script of ours in front of the image's /entrypoint.sh: it passes two plain arguments
    # (tests/deploy/test_router.py runs it through a replica of that entrypoint).
    assert svc["entrypoint"] == ["/bin/sh", "/etc/zenoh/zenohd-start.sh"]
    assert "command" not in svc
    targets = {m.target: m for m in spec.mounts(svc)}
    script = (REPO / targets["/etc/zenoh/zenohd-start.sh"].source).read_text()
    assert 'exec /entrypoint.sh -c "$RUN_DIR/zenohd.json5"' in script
    assert "/run/zenohd" in svc["tmpfs"]
    # zenohd's "Initial conf" line (target zenohd, info) would print the password
    assert spec.environment(svc)["RUST_LOG"].split(",")[-1] == "zenohd=warn"
    # the router logs in to the machine as `machine` and asks Riders for the same dictionary
    assert set(spec.secret_paths(compose, svc, REPO)) == {
        "/run/secrets/machine.password",
        "/run/secrets/zenoh-users",
    }
    conf = zenoh_file(repo_file(targets["/etc/zenoh/zenohd.json5"]))
    assert conf.get_json("mode") == '"router"'
    machine_port = listen_port(REPO / "zenoh.json5")
    assert f'"tcp/machine:{machine_port}"' in conf.get_json("connect/endpoints")
    login = json.loads(conf.get_json("transport/auth/usrpwd"))
    assert login == {
        "user": "machine",
        "password": "@MACHINE_PASSWORD@",
        "dictionary_file": "/run/secrets/zenoh-users",
    }


def test_site_rider_config_is_a_client() -> None:
    conf = zenoh_file(REPO / "docker" / "rider-client.json5")
    assert conf.get_json("mode") == '"client"'
    assert conf.get_json("scouting/multicast/enabled") == "false"


def test_revpi_variant_passes_the_device_and_piCtory_config_only() -> None:
    revpi = spec.service(spec.load_compose(spec.REVPI_OVERRIDE, PICONTROL_ENV), "machine")
    args = spec.parse_cli(spec.command(revpi))
    assert (args.cmd, args.hal) == ("supervise", "revpi")
    procimg = MachineConfig().hal.revpi.procimg
    assert revpi["devices"] == [f"{procimg}:{procimg}"]
    (rsc,) = spec.mounts(revpi)
    assert (rsc.source, rsc.target, rsc.read_only) == (
        "/etc/revpi/config.rsc",
        "/etc/revpi/config.rsc",
        True,
    )
    assert revpi["group_add"] == [PICONTROL_ENV["PICONTROL_GID"]]
    assert not {"privileged", "cap_add", "user"} & revpi.keys()
    with pytest.raises(spec.SpecError, match="PICONTROL_GID"):
        spec.load_compose(spec.REVPI_OVERRIDE, {})
