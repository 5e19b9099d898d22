"""Installed, the project is one import name, `ride_machine`: its wheel installs into a fresh
venv beside PyPI's `schema` (a validation library, and the name of our wire schema's folder in
the repository) and both import, each from its own files; the console scripts run. Issue 54:
the project installed top-level packages named schema, common, service, hal, sim and rider, so
an application using PyPI's `schema` could not import the Rider library beside it."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

from tests.deploy.dockerignore import context_wheel

REPO = Path(__file__).resolve().parents[2]
FOLDERS = ("schema", "common", "hal", "service", "sim", "rider")
WHEELS = Path(sys.prefix) / "wheels"
"""Where `make install` puts requirements/neighbours.txt's wheels (PyPI's `schema`)."""

PROBE = """
import json, schema
import ride_machine.schema.status as status
from ride_machine.rider.client import Rider
assert schema.Schema({"n": int}).validate({"n": 3}) == {"n": 3}
assert status.MachineState.IDLE.value
print(json.dumps({"schema": schema.__file__, "ours": status.__file__, "rider": Rider.__module__}))
"""


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_every_package_of_the_tree_is_in_the_wheel_under_the_one_name() -> None:
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    tree = {
        "ride_machine." + ".".join(init.parent.relative_to(REPO).parts)
        for folder in FOLDERS
        for init in (REPO / folder).rglob("__init__.py")
        if "node_modules" not in init.parts
    }
    assert listed == tree
    mapping = _pyproject()["tool"]["setuptools"]["package-dir"]
    assert mapping == {f"ride_machine.{folder}": folder for folder in FOLDERS}


@pytest.mark.integration
def test_the_wheel_installs_and_imports_beside_pypis_schema(tmp_path: Path) -> None:
    if not list(WHEELS.glob("schema-*.whl")):
        pytest.skip(f"no PyPI schema wheel in {WHEELS}: `make install` downloads it")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    _, wheel = context_wheel(tmp_path, 300.0)  # as the image's builder stage makes it
    install = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-index",
         "--no-deps", "--find-links", str(WHEELS), "schema", str(wheel)],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert install.returncode == 0, install.stdout + install.stderr
    site = Path(
        subprocess.check_output(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            text=True,
        ).strip()
    )
    # Our dependencies (zenoh, pydantic, msgpack) from this venv, offline, after the fresh
    # venv's own packages: a path line adds the folder and runs none of its .pth files.
    (site / "zz_dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")
    probe = subprocess.run(
        [str(python), "-c", PROBE], cwd=tmp_path, capture_output=True, text=True, timeout=120,
        check=False,
    )  # fmt: skip
    assert probe.returncode == 0, probe.stderr
    found = __import__("json").loads(probe.stdout.splitlines()[-1])
    assert Path(found["schema"]) == site / "schema" / "__init__.py"
    assert Path(found["ours"]) == site / "ride_machine" / "schema" / "status.py"
    assert found["rider"].startswith("ride_machine.rider.")  # the façade, wherever it lives
    for script in ("rider", "machine"):
        done = subprocess.run(
            [str(venv / "bin" / script), "--help"], cwd=tmp_path, capture_output=True, text=True,
            timeout=120, check=False,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        assert "usage:" in done.stdout
