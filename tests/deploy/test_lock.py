"""The lock files (requirements/): the same versions for CI and the image, within pyproject's
ranges, every file hash-pinned (requirements/README.md; `make lock` refreshes them)."""

from __future__ import annotations

import importlib.metadata
import re
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from tests.deploy import spec
from tests.procs import REPO

LOCKS = REPO / "requirements"
_PIN = re.compile(r"^([A-Za-z0-9._-]+)==([^\s;\\]+)")


def pins(path: Path) -> dict[str, str]:
    """name → version of each requirement; each must carry at least one sha256 hash."""
    out: dict[str, str] = {}
    text = path.read_text()
    for block in re.split(r"\n(?=\S)", text):
        m = _PIN.match(block)
        if m is None:
            continue
        assert "--hash=sha256:" in block, f"{path.name}: {m[1]} has no hash"
        out[canonical(m[1])] = m[2]
    return out


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def declared() -> list[Requirement]:
    project = spec.pyproject()["project"]
    reqs = list(project["dependencies"])
    for extra in ("dev", "revpi", "ui", "gateway"):
        reqs += project["optional-dependencies"][extra]
    reqs += spec.pyproject()["build-system"]["requires"]
    return [Requirement(r) for r in reqs]


def test_every_declared_dependency_is_locked_within_its_range() -> None:
    dev = pins(LOCKS / "dev.txt")
    for req in declared():
        name = canonical(req.name)
        assert name in dev, f"{req} is not in requirements/dev.txt: run `make lock`"
        assert req.specifier.contains(dev[name], prereleases=True), (
            f"{name}=={dev[name]} is outside {req}: run `make lock`"
        )


def test_the_image_locks_are_the_dev_versions() -> None:
    dev = pins(LOCKS / "dev.txt")
    for name in ("machine.txt", "runtime.txt", "build.txt"):
        image = pins(LOCKS / name)
        assert image, name
        assert {k: dev.get(k) for k in image} == image, f"{name} differs from dev.txt"
    runtime = pins(LOCKS / "runtime.txt")
    project = spec.pyproject()["project"]
    image_reqs = project["dependencies"] + [
        r for e in ("revpi", "ui", "gateway") for r in project["optional-dependencies"][e]
    ]
    assert {canonical(Requirement(r).name) for r in image_reqs} <= runtime.keys()
    machine = pins(LOCKS / "machine.txt")  # the machine's image: no gateway extra
    machine_reqs = project["dependencies"] + [
        r for e in ("revpi", "ui") for r in project["optional-dependencies"][e]
    ]
    assert {canonical(Requirement(r).name) for r in machine_reqs} <= machine.keys()
    assert not {"pytest", "ruff", "mypy", "playwright"} & runtime.keys(), "dev tools in the image"


def test_this_virtualenv_runs_the_locked_versions() -> None:
    """What CI tests is what the image ships (`make install` installs requirements/dev.txt)."""
    if not (Path(sys.prefix) / ".installed").exists():
        pytest.skip("not the Makefile's virtualenv: versions come from elsewhere")
    dev = pins(LOCKS / "dev.txt")
    installed = {}
    for name in dev:
        try:
            installed[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            installed[name] = None
    assert installed == dev, "run `make install` again (requirements/dev.txt changed)"
