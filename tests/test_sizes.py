"""The size rule (STYLE.md): no module over 500 lines, no class over 400, no function over 60,
anywhere outside bench/ (no Python file here is generated: schema/json and docs/states.md are
not Python), with no exceptions. `python -m tests.test_sizes` lists every file over a limit."""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LEFT_OUT = ("bench",)
"""Top-level folders not held to the rule (besides hidden ones, .venv, and npm's node_modules)."""

MODULE_MAX = 500
CLASS_MAX = 400
FUNCTION_MAX = 60


@dataclass(frozen=True)
class Over:
    """One module, class or function past its limit."""

    path: str
    line: int
    what: str
    lines: int
    limit: int

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.what} has {self.lines} lines (at most {self.limit})"


def python_files() -> Iterator[Path]:
    for top in sorted(REPO.iterdir()):
        if top.name in LEFT_OUT or top.name.startswith("."):
            continue
        found = [top] if top.suffix == ".py" else sorted(top.rglob("*.py")) if top.is_dir() else []
        yield from (path for path in found if "node_modules" not in path.parts)


def oversized(path: Path, root: Path = REPO) -> Iterator[Over]:
    """What in `path` is past its limit: the module, then its classes and functions (nested
    ones too), measured from the `class`/`def` line to the last line of the body."""
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
    found = {(o.what, o.lines) for o in oversized(path, tmp_path)}
    assert ("function f", FUNCTION_MAX + 1) in found
    assert ("the module", FUNCTION_MAX + 2 + MODULE_MAX - 60) in found
    assert not any(what == "class A" for what, _ in found)  # 62 lines: within its limit


def main() -> int:
    """Every module, class and function over its limit (there are no exceptions)."""
    found = everything_over()
    for over in found:
        print(over)
    print(f"{len(found)} over a limit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
