"""The import graph keeps its arrows: schema ← hal ← service, hal ← sim, rider ← schema, and
common (what daemon and Rider share off the wire: the session, the logins, how events read for
people) on schema; schema holds wire models on
pydantic, msgpack and the standard library alone; the simulator is a HAL backend found by name
(`hal.backends`), imported by nothing outside sim/; Zenoh only at the edges; no cycles."""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("schema", "common", "hal", "service", "sim", "rider")

MAY_IMPORT = {
    "schema": set(),
    "common": {"schema"},
    "hal": {"schema"},
    "service": {"hal", "schema", "common"},
    "sim": {"hal", "schema"},
    "rider": {"schema", "common"},
}
"""Which of our packages each package may import (besides itself), at the top or on use."""

SCHEMA_LIBRARIES = {"pydantic", "msgpack"}
"""Besides the standard library, all the wire schema may import: any client in Python can
read our messages with these two."""

ZENOH_MODULES = (
    "service/bus/",
    "common/zenoh_session.py",
    "rider/blocking.py",
    "rider/completions.py",
    "rider/confirm.py",
    "rider/discovery.py",
    "rider/events.py",
    "rider/link.py",
    "rider/machines.py",
    "rider/pinning.py",
    "rider/replies.py",
    "rider/subscriptions.py",
    "rider/transport.py",
    "rider/gateway/bus.py",
)
"""Where `zenoh` may be imported: the machine's bus, the Rider's client side (the plant
gateway's own session included), and the one module both sides open their sessions with (the
config from zenoh.json5, the secrets, the runtime: written once, not once per side)."""


def modules() -> Iterator[Path]:
    for package in PACKAGES:
        yield from sorted((REPO / package).rglob("*.py"))


INSTALLED_AS = "ride_machine."
"""The one import name everything installed sits under (pyproject.toml's package-dir)."""


def _ours(name: str) -> str:
    """`name` as the folders at the top name it: ride_machine.service.cli → service.cli."""
    return name.removeprefix(INSTALLED_AS)


def imports(path: Path) -> Iterator[tuple[str, int]]:
    """Every module name `path` imports (at the top, in a function, under TYPE_CHECKING),
    relative imports resolved, our own named by their folders (service.cli)."""
    tree = ast.parse(path.read_text(), str(path))
    here = rel(path).removesuffix(".py").split("/")
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield _ours(alias.name), node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(here[: len(here) - node.level])
                module = f"{base}.{node.module}" if node.module else base
            elif node.module:
                module = _ours(node.module)
            else:
                continue
            yield module, node.lineno
            for alias in node.names:  # `from service import bus` imports service.bus
                yield f"{module}.{alias.name}", node.lineno


def rel(path: Path) -> str:
    return path.relative_to(REPO).as_posix()


def test_every_package_imports_only_down_its_arrows() -> None:
    wrong = []
    for path in modules():
        own = rel(path).split("/", 1)[0]
        for name, line in imports(path):
            top = name.split(".", 1)[0]
            if top in PACKAGES and top != own and top not in MAY_IMPORT[own]:
                wrong.append(f"{rel(path)}:{line} imports {name} ({own} may not import {top})")
    assert not wrong, "\n".join(wrong)


def test_our_code_is_imported_by_its_installed_name() -> None:
    """Installed, the folders are ride_machine.<folder> (pyproject.toml's package-dir): an
    import by a bare folder name (`import schema`) works only from the repository, and where
    PyPI's `schema` is installed it takes that one."""
    wrong = []
    trees = [REPO / top for top in ("tests", "bench", "docker")]
    paths = [*modules(), *(p for top in trees for p in sorted(top.rglob("*.py")))]
    for path in paths:
        if "node_modules" in path.parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            bare = [name for name in names if name.split(".", 1)[0] in PACKAGES]
            wrong += [f"{rel(path)}:{node.lineno} imports {name}" for name in bare]
    assert not wrong, "\n".join(wrong)


def test_schema_imports_only_pydantic_msgpack_and_the_standard_library() -> None:
    wrong = [
        f"{rel(path)}:{line} imports {name}"
        for path in sorted((REPO / "schema").rglob("*.py"))
        for name, line in imports(path)
        if (top := name.split(".", 1)[0]) != "schema"
        and top not in SCHEMA_LIBRARIES
        and top not in sys.stdlib_module_names
    ]
    assert not wrong, "\n".join(wrong)


def test_zenoh_is_imported_only_by_the_bus_and_the_rider_client() -> None:
    wrong = [
        f"{rel(path)}:{line}"
        for path in modules()
        for name, line in imports(path)
        if name.split(".", 1)[0] == "zenoh" and not rel(path).startswith(ZENOH_MODULES)
    ]
    assert not wrong, wrong


def test_nothing_outside_the_simulator_imports_it() -> None:
    """The code that runs never imports the code that simulates: the daemon, the supervisor
    and the config reach it by name (`hal.backends.backend("sim")`, tests/hal/test_backends.py)."""
    users = {rel(p) for p in modules() for name, _ in imports(p) if name.split(".")[0] == "sim"}
    assert {u for u in users if not u.startswith("sim/")} == set()


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of `graph` (as a path that returns to its start), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def package_graph() -> dict[str, set[str]]:
    """Edges between our packages."""
    graph: dict[str, set[str]] = {p: set() for p in PACKAGES}
    for path in modules():
        own = rel(path).split("/", 1)[0]
        for name, _ in imports(path):
            top = name.split(".", 1)[0]
            if top in PACKAGES and top != own:
                graph[own].add(top)
    return graph


def subpackage_graph(package: str) -> dict[str, set[str]]:
    """Edges between the sub-packages (folders) of `package` (dotted: service.core too)."""
    root = REPO.joinpath(*package.split("."))
    depth = package.count(".") + 1
    subs = {p.parent.name for p in root.glob("*/__init__.py")}
    graph: dict[str, set[str]] = {s: set() for s in subs}
    own = package.split(".")
    for sub in subs:
        for path in (root / sub).rglob("*.py"):
            for name, _ in imports(path):
                parts = name.split(".")
                inner = parts[depth] if parts[:depth] == own and len(parts) > depth else ""
                if inner in subs - {sub}:
                    graph[sub].add(inner)
    return graph


def test_no_import_cycle_between_packages() -> None:
    assert _cycle(package_graph()) is None


@pytest.mark.parametrize("package", [*PACKAGES, "ride_machine.service.core"])
def test_no_import_cycle_between_sub_packages(package: str) -> None:
    assert _cycle(subpackage_graph(package)) is None


def module_of(name: str) -> Path | None:
    """The file of ours that importing `name` runs last (a module, or a package's
    __init__.py), or None when `name` is not ours or names a class or function in one."""
    path = REPO.joinpath(*name.split("."))
    for found in (path.with_suffix(".py"), path / "__init__.py"):
        if name.split(".", 1)[0] in PACKAGES and found.is_file():
            return found
    return None


def module_graph() -> dict[str, set[str]]:
    """Edges between our modules (files): every import counts, at the top, in a function or
    under TYPE_CHECKING, since each ties the two files' designs together. A module's own
    packages (the __init__.py of each folder it sits in) are no edge: Python runs them before
    the module whatever it imports, and `from package import sibling` names one of them."""
    graph: dict[str, set[str]] = {}
    for path in modules():
        targets = {module_of(name) for name, _ in imports(path)} - {None, path}
        own = {folder / "__init__.py" for folder in path.parents}
        graph[rel(path)] = {rel(t) for t in targets if t is not None and t not in own}
    return graph


def test_no_import_cycle_between_modules() -> None:
    """No two files of the product import each other, however far round (issue 54)."""
    assert _cycle(module_graph()) is None


def test_the_module_graph_has_the_arrows_the_code_has() -> None:
    """The edges name real files (the CLI's config loading among them), and no module is
    drawn importing its own folder's face."""
    graph = module_graph()
    assert all((REPO / target).is_file() for targets in graph.values() for target in targets)
    assert "service/config/load.py" in graph["service/cli.py"]
    assert (
        "service/core/statemachine/__init__.py" not in graph["service/core/statemachine/machine.py"]
    )


def test_the_cycle_check_finds_a_cycle() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None
