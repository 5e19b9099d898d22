"""The hazard log: docs/hazards.toml made into docs/hazards.md, and the checks that keep it true.

Each hazard of the table (ISO 12100's chain: hazard, situation, event, harm; the risk before
and after) names its measures, the level each lives on, the tests that prove each measure and,
where a benchmark measures one, the figure. Every test named there carries
`@pytest.mark.hazard("Hnn")`, and every test so marked is named there; the page shows each
test's result of the last `make hazards` and each figure's value and date, read from
BENCHMARKS.md (marked stale when the benchmark's script changed after it was measured).

    python -m tests.hazard_log          # docs/hazards.md from the table and the recorded results
    python -m tests.hazard_log --run    # first run every hazard test and record the results
                                        # (`make hazards`)

tests/test_hazards.py fails on drift: a hazard without a test, a named test that is gone, a
marked test the table does not name, a page that differs from what this writes. The page's
prose lives in the table too (`[page]`); the rendering is in `tests.hazard_page`.
"""

from __future__ import annotations

import ast
import datetime
import hashlib
import json
import subprocess
import sys
import tempfile
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

REPO = Path(__file__).resolve().parent.parent
TABLE = REPO / "docs" / "hazards.toml"
PAGE = REPO / "docs" / "hazards.md"
RESULTS = REPO / "docs" / "hazard-results.json"
BENCHMARKS = REPO / "BENCHMARKS.md"
TESTS = REPO / "tests"
MARKER = "hazard"


class Level(StrEnum):
    """Where a measure lives, inside out."""

    SCAN_LOOP = "scan loop"
    WATCHDOG = "in-process watchdog"
    SUPERVISOR = "supervisor"
    CHARGE_PUMP = "charge pump"
    RIDER = "rider"
    ACCESS_CONTROL = "access control"
    CONFIG_CHECK = "config check"
    STORAGE = "storage"
    HARDWARE = "hardware"
    PROCEDURE = "procedure"


SOFTWARE_FREE = frozenset({Level.HARDWARE, Level.PROCEDURE})
"""Levels whose measures no test of ours can prove."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Risk(_Model):
    severity: int = Field(ge=1, le=4)
    """1 minor … 4 fatal."""
    likelihood: int = Field(ge=1, le=5)
    """1 improbable … 5 frequent."""


class Figure(_Model):
    """One cell of a benchmark's table in BENCHMARKS.md."""

    section: str
    """The benchmark (`<!-- bench:NAME -->`; its script is bench/NAME.py)."""
    table: str
    """How the table's bold title begins."""
    row: list[str]
    """The first cells of the row."""
    column: str
    label: str
    """What the value is, for the page ("relays off, p99")."""
    unit: str = ""


class Measure(_Model):
    level: Level
    text: str
    tests: list[str] = []
    figure: Figure | None = None


class Hazard(_Model):
    id: str = Field(pattern=r"^H\d{2}$")
    title: str
    group: str
    hazard: str
    situation: str
    event: str
    harm: str
    before: Risk
    after: Risk
    residual: str
    software: bool
    measure: list[Measure]

    def tests(self) -> list[str]:
        return [t for m in self.measure for t in m.tests]


class Page(_Model):
    """The page's prose: what the log is, what the hardware must do, commissioning."""

    intro: str
    hardware: list[str]
    checklist: list[str]


class Log(_Model):
    page: Page
    hazard: list[Hazard]


def load(path: Path = TABLE) -> Log:
    return Log.model_validate(tomllib.loads(path.read_text()))


# ---------------------------------------------------------------------- tests and markers
@dataclass(frozen=True)
class Suite:
    """The suite as its files say, read without running it: every test's node id (without
    parameters) and the hazards each is marked for."""

    tests: frozenset[str]
    marked: dict[str, frozenset[str]]


def scan(root: Path = TESTS) -> Suite:
    tests: set[str] = set()
    marked: dict[str, frozenset[str]] = {}
    for path in sorted(root.rglob("test_*.py")):
        rel = path.relative_to(root.parent).as_posix()
        tree = ast.parse(path.read_text(), rel)
        module = _marks(_module_marks(tree))
        for node_id, decorators in _tests_in(tree, rel):
            tests.add(node_id)
            hazards = module | _marks(decorators)
            if hazards:
                marked[node_id] = frozenset(hazards)
    return Suite(frozenset(tests), marked)


def _tests_in(tree: ast.Module, rel: str) -> Iterator[tuple[str, list[ast.expr]]]:
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name.startswith(
            "test"
        ):
            yield f"{rel}::{node.name}", node.decorator_list
        elif isinstance(node, ast.ClassDef) and node.name.startswith("Test"):
            for item in node.body:
                if isinstance(item, ast.FunctionDef) and item.name.startswith("test"):
                    yield (
                        f"{rel}::{node.name}::{item.name}",
                        [
                            *node.decorator_list,
                            *item.decorator_list,
                        ],
                    )


def _module_marks(tree: ast.Module) -> list[ast.expr]:
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets
        ):
            value = node.value
            return list(value.elts) if isinstance(value, ast.List | ast.Tuple) else [value]
    return []


def _marks(exprs: list[ast.expr]) -> set[str]:
    """The hazard ids of every `pytest.mark.hazard("H01", …)` among `exprs`."""
    out: set[str] = set()
    for expr in exprs:
        if (
            isinstance(expr, ast.Call)
            and isinstance(expr.func, ast.Attribute)
            and expr.func.attr == MARKER
        ):
            out |= {
                a.value
                for a in expr.args
                if isinstance(a, ast.Constant) and isinstance(a.value, str)
            }
    return out


def problems(log: Log, suite: Suite) -> list[str]:
    """Every way the table and the suite disagree (none: they tell one story)."""
    ids = [h.id for h in log.hazard]
    out = [f"{i} appears {ids.count(i)} times" for i in sorted(set(ids)) if ids.count(i) > 1]
    for h in log.hazard:
        out += _measure_problems(h)
        out += _named_problems(h, suite)
    return out + _marked_problems(log, suite)


def _measure_problems(h: Hazard) -> list[str]:
    """A hazard's measures against its `software` flag, and against what tests can prove."""
    out = []
    if h.software and not h.tests():
        out.append(f"{h.id} ({h.title}) has no test")
    if not h.software and any(m.level not in SOFTWARE_FREE for m in h.measure):
        out.append(f"{h.id} says no software covers it, yet names a software measure")
    for m in h.measure:
        if m.level in SOFTWARE_FREE and m.tests:
            out.append(f"{h.id}: a {m.level} measure cannot be proven by our tests")
        if m.level not in SOFTWARE_FREE and not m.tests:
            out.append(f"{h.id}: its {m.level} measure names no test")
    return out


def _named_problems(h: Hazard, suite: Suite) -> list[str]:
    """Each test a hazard names: it exists, and carries the hazard's marker."""
    out = []
    for test in sorted(set(h.tests())):
        if test not in suite.tests:
            out.append(f"{h.id}: {test} does not exist")
        elif h.id not in suite.marked.get(test, ()):
            out.append(f'{h.id}: {test} is named but not marked @pytest.mark.hazard("{h.id}")')
    return out


def _marked_problems(log: Log, suite: Suite) -> list[str]:
    """Each marked test: its hazard exists and names it."""
    by_id = {h.id: h for h in log.hazard}
    out = []
    for test, hazards in sorted(suite.marked.items()):
        for hid in sorted(hazards):
            if hid not in by_id:
                out.append(f"{test} is marked for {hid}, which the table does not have")
            elif test not in by_id[hid].tests():
                out.append(f"{test} is marked for {hid}, but {hid} does not name it")
    return out


# ---------------------------------------------------------------------- results
class BenchStamp(_Model):
    """A benchmark's script as it was when its section was measured."""

    sha: str
    measured: str


class RunResult(_Model):
    outcome: str
    """passed, failed or skipped (a parametrized test: failed if any case failed)."""
    at: str


class Results(_Model):
    run: str | None = None
    tests: dict[str, RunResult] = {}
    benches: dict[str, BenchStamp] = {}


def load_results(path: Path = RESULTS) -> Results:
    if not path.exists():
        return Results()
    return Results.model_validate_json(path.read_text())


def script_sha(section: str) -> str:
    return hashlib.sha256((REPO / "bench" / f"{section}.py").read_bytes()).hexdigest()[:16]


def stamp_benches(log: Log, results: Results, benchmarks: str) -> dict[str, BenchStamp]:
    """Each figure's benchmark as of now: the script's hash is taken again only when the section
    was measured again since (so a script changed after its measurement stays told apart)."""
    out = dict(results.benches)
    sections = {m.figure.section for h in log.hazard for m in h.measure if m.figure}
    for section in sorted(sections):
        measured = measured_line(benchmarks, section)
        old = out.get(section)
        if old is None or old.measured != measured:
            out[section] = BenchStamp(sha=script_sha(section), measured=measured)
    return out


def measured_line(benchmarks: str, section: str) -> str:
    """ "2026-12-02 05:46 UTC": when the section was last measured."""
    body = bench_section(benchmarks, section)
    first = body.strip().splitlines()[0]
    if not first.startswith("Measured "):
        raise ValueError(f"section {section}: no 'Measured …' line")
    return first.removeprefix("Measured ").split(" with ")[0]


def bench_section(benchmarks: str, section: str) -> str:
    start, end = f"<!-- bench:{section} -->", f"<!-- /bench:{section} -->"
    if start not in benchmarks:
        raise ValueError(f"BENCHMARKS.md has no section {section!r}")
    return benchmarks.split(start, 1)[1].split(end, 1)[0]


def figure_value(benchmarks: str, figure: Figure) -> str:
    """The cell a figure names, or a ValueError that says which part was not found."""
    body = bench_section(benchmarks, figure.section)
    blocks = body.split("**")
    for i in range(1, len(blocks) - 1, 2):
        if not blocks[i].startswith(figure.table):
            continue
        rows = [
            [c.strip() for c in line.strip().strip("|").split("|")]
            for line in blocks[i + 1].splitlines()
            if line.startswith("|")
        ]
        header, body_rows = rows[0], rows[2:]
        if figure.column not in header:
            raise ValueError(f"{figure.section}: no column {figure.column!r} in {header}")
        col = header.index(figure.column)
        for row in body_rows:
            if row[: len(figure.row)] == figure.row:
                return row[col]
        raise ValueError(f"{figure.section}: no row {figure.row} in {figure.table!r}")
    raise ValueError(f"{figure.section}: no table {figure.table!r}")


def run_tests(log: Log) -> dict[str, RunResult]:
    """Every test the table names, run once (two workers, a file at a time), by outcome."""
    tests = sorted({t for h in log.hazard for t in h.tests()})
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "junit.xml"
        cmd = [sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadfile"]
        subprocess.run([*cmd, f"--junitxml={report}", *tests], cwd=REPO, check=False)
        cases = ET.parse(report).getroot().iter("testcase")
        now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
        outcomes: dict[str, str] = {}
        for case in cases:
            node = _node_id(case.get("classname", ""), case.get("name", ""))
            outcome = _outcome(case)
            before = outcomes.get(node)
            if before is None or before == "skipped" or outcome == "failed":
                outcomes[node] = outcome if before != "failed" else "failed"
    return {n: RunResult(outcome=outcomes.get(n, "not run"), at=now) for n in tests}


def _node_id(classname: str, name: str) -> str:
    """junit's `tests.a.test_b` (or `tests.a.test_b.TestC`) and `test_d[x]` as a node id."""
    parts = classname.split(".")
    cls = [parts.pop()] if parts and parts[-1][:1].isupper() else []
    return "::".join(["/".join(parts) + ".py", *cls, name.split("[", maxsplit=1)[0]])


def _outcome(case: ET.Element) -> str:
    if case.find("failure") is not None or case.find("error") is not None:
        return "failed"
    if case.find("skipped") is not None:
        return "skipped"
    return "passed"


def main(argv: list[str] | None = None) -> int:
    from tests.hazard_page import render

    args = sys.argv[1:] if argv is None else argv
    log = load()
    found = problems(log, scan())
    if found:
        print("\n".join(f"hazards: {p}" for p in found), file=sys.stderr)
        return 1
    results = load_results()
    benchmarks = BENCHMARKS.read_text()
    if "--run" in args:
        tests = run_tests(log)
        now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
        results = Results(run=now, tests=tests, benches=stamp_benches(log, results, benchmarks))
        RESULTS.write_text(json.dumps(results.model_dump(), indent=1, sort_keys=True) + "\n")
    PAGE.write_text(render(log, results, benchmarks))
    print(f"wrote {PAGE.relative_to(REPO)}: {len(log.hazard)} hazards")
    return 0


if __name__ == "__main__":
    sys.exit(main())
