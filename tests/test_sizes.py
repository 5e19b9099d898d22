"""The size rule (STYLE.md): no module over 450 lines, no class over 400 lines or 30 methods, no
function over 60 lines, anywhere outside bench/ (no Python file here is generated: schema/json
and docs/states.md are not Python), with one exception, `MANY_METHODS_ALLOWED`.
`python -m tests.test_sizes` lists everything over a limit."""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LEFT_OUT = ("bench",)
"""Top-level folders not held to the rule (besides hidden ones, .venv, and npm's node_modules)."""

MODULE_MAX = 450
CLASS_MAX = 400
FUNCTION_MAX = 60
METHODS_MAX = 30
"""Methods (functions defined in the class's own body: properties and dunders too) a class."""

MANY_METHODS_ALLOWED = {
    "rider/blocking.py:Rider": "the Rider's typed façade: a short method per command, read,"
    " event query, subscription and wait, each handing the call to its part (rider/commands.py,"
    " reads.py, subscriptions.py ...), so a user's editor shows every call with its signature",
}
"""Classes allowed more than `METHODS_MAX` methods, with the reason (`path:Class`)."""


@dataclass(frozen=True)
class Over:
    """One module, class or function past its limit."""

    path: str
    line: int
    what: str
    size: int
    limit: int
    unit: str = "lines"
    """What `size` and `limit` count: lines, or (a class) methods."""

    def __str__(self) -> str:
        where = f"{self.path}:{self.line}"
        return f"{where}: {self.what} has {self.size} {self.unit} (at most {self.limit})"


def python_files() -> Iterator[Path]:
    for top in sorted(REPO.iterdir()):
        if top.name in LEFT_OUT or top.name.startswith("."):
            continue
        found = [top] if top.suffix == ".py" else sorted(top.rglob("*.py")) if top.is_dir() else []
        yield from (path for path in found if "node_modules" not in path.parts)


def oversized(path: Path, root: Path = REPO) -> Iterator[Over]:
    """What in `path` is past its limit: the module, then its classes and functions (nested
    ones too), measured from the `class`/`def` line to the last line of the body, and each
    class's methods counted."""
    rel = path.relative_to(root).as_posix()
    text = path.read_text()
    lines = len(text.splitlines())
    if lines > MODULE_MAX:
        yield Over(rel, 1, "the module", lines, MODULE_MAX)
    for node in ast.walk(ast.parse(text, rel)):
        if isinstance(node, ast.ClassDef):
            kind, limit = "class", CLASS_MAX
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            kind, limit = "function", FUNCTION_MAX
        else:
            continue
        size = (node.end_lineno or node.lineno) - node.lineno + 1
        if size > limit:
            yield Over(rel, node.lineno, f"{kind} {node.name}", size, limit)
        if isinstance(node, ast.ClassDef) and f"{rel}:{node.name}" not in MANY_METHODS_ALLOWED:
            methods = sum(isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef) for b in node.body)
            if methods > METHODS_MAX:
                yield Over(rel, node.lineno, f"class {node.name}", methods, METHODS_MAX, "methods")


def everything_over() -> list[Over]:
    return [over for path in python_files() for over in oversized(path)]


def test_no_module_class_or_function_is_over_its_limit() -> None:
    found = [str(over) for over in everything_over()]
    assert not found, "past the size rule (STYLE.md):\n" + "\n".join(found)


def test_the_rule_sees_a_long_function_class_and_module(tmp_path: Path) -> None:
    body = "\n".join(f"        x{i} = {i}" for i in range(FUNCTION_MAX))
    source = f"class A:\n    def f(self) -> None:\n{body}\n" + "\n" * (MODULE_MAX - 60)
    path = tmp_path / "probe.py"
    path.write_text(source)
    found = {(o.what, o.size) for o in oversized(path, tmp_path) if o.unit == "lines"}
    assert ("function f", FUNCTION_MAX + 1) in found
    assert ("the module", FUNCTION_MAX + 2 + MODULE_MAX - 60) in found
    assert not any(what == "class A" for what, _ in found)  # 62 lines: within its limit


def test_the_rule_counts_a_class_s_methods(tmp_path: Path) -> None:
    def probe(name: str, cls: str, methods: int) -> set[tuple[str, int, str]]:
        body = "".join(f"    def m{i}(self) -> None:\n        pass\n" for i in range(methods))
        path = tmp_path / name
        path.parent.mkdir(exist_ok=True)
        path.write_text(f"class {cls}:\n{body}")
        return {(o.what, o.size, o.unit) for o in oversized(path, tmp_path)}

    assert probe("many.py", "B", METHODS_MAX + 1) == {("class B", METHODS_MAX + 1, "methods")}
    assert probe("enough.py", "B", METHODS_MAX) == set()
    # The one exception is a class of one module, not a name.
    assert probe("rider/blocking.py", "Rider", METHODS_MAX + 1) == set()
    assert probe("rider/other.py", "Rider", METHODS_MAX + 1) != set()


def main() -> int:
    """Every module, class and function over its limit (`MANY_METHODS_ALLOWED` left out)."""
    found = everything_over()
    for over in found:
        print(over)
    print(f"{len(found)} over a limit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
