"""The import graph keeps its arrows: schema ← hal ← service ← sim, rider ← schema; nothing in
production imports the simulator wing but its one door; Zenoh only at the edges; no cycles."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("schema", "hal", "service", "sim", "rider")

MAY_IMPORT = {
    "schema": set(),
    "hal": {"schema"},
    "service": {"hal", "schema"},
    "sim": {"hal", "schema", "service"},
    "rider": {"schema"},
}
"""Which of our packages each package may import (besides itself)."""

SIM_DOOR = "service/simwing.py"
"""The composition point: the only production module that imports `sim` (lazily)."""

ZENOH_MODULES = (
    "service/bus/",
    "rider/blocking.py",
    "rider/completions.py",
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
"""Where `zenoh` may be imported: the machine's bus and the Rider's client side (the plant
gateway's own session included)."""


def modules() -> Iterator[Path]:
    for package in PACKAGES:
        yield from sorted((REPO / package).rglob("*.py"))


def imports(path: Path) -> Iterator[tuple[str, int]]:
    """Every module name `path` imports (at the top, in a function, under TYPE_CHECKING)."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module, node.lineno
            for alias in node.names:  # `from service import bus` imports service.bus
                yield f"{node.module}.{alias.name}", node.lineno


def rel(path: Path) -> str:
    return path.relative_to(REPO).as_posix()


def test_every_package_imports_only_down_its_arrows() -> None:
    wrong = []
    for path in modules():
        own = rel(path).split("/", 1)[0]
        for name, line in imports(path):
            top = name.split(".", 1)[0]
            if top in PACKAGES and top != own and top not in MAY_IMPORT[own]:
                if top == "sim" and rel(path) == SIM_DOOR:
                    continue
                wrong.append(f"{rel(path)}:{line} imports {name} ({own} may not import {top})")
    assert not wrong, "\n".join(wrong)


def test_zenoh_is_imported_only_by_the_bus_and_the_rider_client() -> None:
    wrong = [
        f"{rel(path)}:{line}"
        for path in modules()
        for name, line in imports(path)
        if name.split(".", 1)[0] == "zenoh" and not rel(path).startswith(ZENOH_MODULES)
    ]
    assert not wrong, wrong


def test_the_simulator_wing_has_one_door_and_it_opens_on_use() -> None:
    door = REPO / SIM_DOOR
    tree = ast.parse(door.read_text())
    top_level = [
        node
        for node in tree.body
        if isinstance(node, ast.Import | ast.ImportFrom)
        for name in imports_of(node)
        if name.split(".", 1)[0] == "sim"
    ]
    assert not top_level, "service/simwing.py must import sim inside its functions only"
    users = {rel(p) for p in modules() for name, _ in imports(p) if name.split(".")[0] == "sim"}
    assert {u for u in users if not u.startswith("sim/")} == {SIM_DOOR}


def imports_of(node: ast.Import | ast.ImportFrom) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    return [node.module or ""]


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
    """Edges between our packages; the door's own imports of `sim` run on use only, after both
    packages have loaded, so they close no cycle."""
    graph: dict[str, set[str]] = {p: set() for p in PACKAGES}
    for path in modules():
        own = rel(path).split("/", 1)[0]
        for name, _ in imports(path):
            top = name.split(".", 1)[0]
            if top == "sim" and rel(path) == SIM_DOOR:
                continue
            if top in PACKAGES and top != own:
                graph[own].add(top)
    return graph


def subpackage_graph(package: str) -> dict[str, set[str]]:
    """Edges between the sub-packages (folders) of `package`."""
    root = REPO / package
    subs = {p.parent.name for p in root.glob("*/__init__.py")}
    graph: dict[str, set[str]] = {s: set() for s in subs}
    for sub in subs:
        for path in (root / sub).rglob("*.py"):
            for name, _ in imports(path):
                parts = name.split(".")
                if len(parts) > 1 and parts[0] == package and parts[1] in subs - {sub}:
                    graph[sub].add(parts[1])
    return graph


def test_no_import_cycle_between_packages() -> None:
    assert _cycle(package_graph()) is None


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycle_between_sub_packages(package: str) -> None:
    assert _cycle(subpackage_graph(package)) is None


def test_the_cycle_check_finds_a_cycle() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None
