"""compose.yaml and its override files checked against the package, the image and the repo.

There is no container engine here, so each deployment file is parsed and every claim it makes
is checked where it can fail: commands go through the package's own argparse parsers, mounted
files must exist, ports and machine ids must agree across files and with the image (the
Dockerfile's own checks are in test_dockerfile.py, the hardening's in test_hardening.py).
"""

from __future__ import annotations

import inspect
import re
import shlex
import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import zenoh

from ride_machine.service.adapters.credentials import DICTIONARY, identities, password_file
from ride_machine.service.adapters.heartbeat import HEARTBEAT_FILE_ENV, INTERVAL_S
from ride_machine.service.adapters.opcua_credentials import opcua_files
from ride_machine.service.bus import close_session
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.supervision.daemon import SHUTDOWN_DEADLINE_S
from tests.deploy import spec
from tests.procs import REPO

UID = 10001
BUILD_TIMEOUT_S = 120.0
LINT_TIMEOUT_S = 60.0
PICONTROL_ENV = {"PICONTROL_GID": "996"}
ROUTER_PROGRAM = "/opt/site-router/site_router.py"
SITE_CA = "./secrets/site-ca.crt"
PROJECT_DIR = "./"  # the logins check's mount: the directory itself (test_logins_check.py)
RIDERS_PORT, SITE_PORT = 7447, 7448


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
    """No `profiles:` anywhere: podman-compose 1.0.3 ignores them and starts every service.
    The `logins` check runs before them (test_logins_check.py)."""
    assert set(compose["services"]) == {"logins", "machine", "rider"}
    # the machine dials its router; the router's login files join the check
    assert set(router["services"]) == {"logins", "router", "machine"}
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
                assert m.read_only, f"{name}: {m.source} should be mounted :ro"
                if m.source == SITE_CA or (name, m.source) == ("logins", PROJECT_DIR):
                    continue  # made by docker/site-certs.sh on the site, like the secrets
                assert repo_file(m).is_file(), f"{name}: {m.source} is not a file in the repo"
                assert repo_file(m).is_relative_to(REPO), f"{name}: {m.source} leaves the repo"


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
    for name, svc in [*compose["services"].items(), ("router", spec.service(router, "router"))]:
        # the logins check runs once per `up`, and again only with the next
        assert svc.get("restart") == ("no" if name == "logins" else "unless-stopped"), name
        assert svc.get("stop_signal", "SIGTERM") == "SIGTERM", name
    grace = spec.seconds(spec.service(compose, "machine")["stop_grace_period"])
    # Outputs go safe at once; the grace period must outlast the bounded Zenoh close after it.
    close_bound = inspect.signature(close_session).parameters["timeout"].default
    assert grace >= close_bound + 2.0
    # under the supervisor: the child's own stop deadline, then the supervisor's close
    assert grace >= SHUTDOWN_DEADLINE_S + close_bound


def test_every_service_rotates_its_log(compose: dict[str, Any], router: dict[str, Any]) -> None:
    """An edge box logs to an SD card: json-file with a size cap on every service."""
    for name, svc in [*compose["services"].items(), ("router", spec.service(router, "router"))]:
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
    # host loopback by default; opening it to the site is a documented edit
    assert spec.service(router, "router")["ports"] == [
        f"127.0.0.1:{p}:{p}" for p in (RIDERS_PORT, SITE_PORT)
    ]


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


def test_router_runs_the_image_with_the_machines_own_profile(
    compose: dict[str, Any], router: dict[str, Any]
) -> None:
    """Issue 57: the router enforces the machine's logins and rules, read from the same file
    (tests/deploy/test_site_router.py runs the service); its program is in the image."""
    svc = spec.service(router, "router")
    assert svc["image"] == spec.service(compose, "machine")["image"]
    argv = spec.command(svc)
    assert argv[:2] == ["python", ROUTER_PROGRAM]
    targets = {m.target: m for m in spec.mounts(svc)}
    profile = argv[argv.index("--zenoh-config") + 1]
    machine_profile = str(
        spec.parse_cli(spec.command(spec.service(compose, "machine"))).zenoh_config
    )
    machine_targets = {m.target: m for m in spec.mounts(spec.service(compose, "machine"))}
    assert targets[profile].source == machine_targets[machine_profile].source == "./zenoh/acl.json5"
    env = spec.environment(svc)
    secrets = spec.secret_paths(spec.merged(compose, router), svc, REPO / "secrets")
    assert secrets[env["MACHINE_ZENOH_DICTIONARY_FILE"]].name == DICTIONARY
    assert env["MACHINE_ZENOH_USER"] == "router"
    assert secrets[env["MACHINE_ZENOH_PASSWORD_FILE"]] == password_file(REPO / "secrets", "router")
    for var in ("TLS_CERTIFICATE", "TLS_PRIVATE_KEY"):
        assert env[f"MACHINE_ZENOH_{var}"] in secrets, var
    assert targets[env["MACHINE_ZENOH_TLS_ROOT_CA"]].source == SITE_CA
    listen = [argv[i + 1] for i, a in enumerate(argv) if a == "--listen"]
    assert listen == [f"tcp/0.0.0.0:{RIDERS_PORT}", f"tls/0.0.0.0:{SITE_PORT}"]
    copied = [
        spec.exec_form(i.args) if i.args.startswith("[") else i.args.split()
        for i in spec.image(spec.dockerfile())
        if i.keyword == "COPY"
    ]
    assert ["docker/site_router.py", str(Path(ROUTER_PROGRAM).parent) + "/"] in copied


def test_the_machine_dials_its_router_with_compose_yamls_command(
    compose: dict[str, Any], router: dict[str, Any]
) -> None:
    """The override repeats the machine's command (compose replaces a list): nothing but the
    router's TLS endpoint may differ, and the site's CA is what it checks the router by."""
    base = spec.command(spec.service(compose, "machine"))
    over = spec.service(router, "machine")
    assert spec.command(over) == [*base, "--connect", f"tls/router:{SITE_PORT}"]
    ca = spec.environment(over)["MACHINE_ZENOH_TLS_ROOT_CA"]
    assert {m.target: m.source for m in spec.mounts(over)}[ca] == SITE_CA
    merged = spec.service(spec.merged(compose, router), "machine")
    assert spec.environment(merged)["MACHINE_ZENOH_USER"] == "machine"  # kept from compose.yaml


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
