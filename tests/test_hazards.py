"""The hazard log cannot drift (issue 55): docs/hazards.toml, the tests' `hazard` markers, the
suite and docs/hazards.md tell one story, and the checker finds each kind of drift."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from tests.hazard_log import (
    BENCHMARKS,
    PAGE,
    BenchStamp,
    Figure,
    Log,
    Results,
    RunResult,
    Suite,
    figure_value,
    load,
    load_results,
    problems,
    scan,
    script_sha,
)
from tests.hazard_page import figure, render

MIN_HAZARDS = 30


def test_the_table_and_the_suite_agree() -> None:
    assert problems(load(), scan()) == []


def test_the_page_is_what_make_hazards_writes() -> None:
    written = render(load(), load_results(), BENCHMARKS.read_text())
    assert PAGE.read_text() == written, "docs/hazards.md is stale: run `make hazards`"


def test_the_log_covers_what_a_certifier_asks_for() -> None:
    log = load()
    assert len(log.hazard) >= MIN_HAZARDS
    for h in log.hazard:
        assert h.after.likelihood <= h.before.likelihood, h.id
        if h.software:
            assert h.tests(), h.id


# ------------------------------------------------------------------ the checker, checked
def tiny_log(tests: list[str], software: bool = True) -> Log:
    level = "scan loop" if software else "hardware"
    return Log.model_validate(
        {
            "page": {"intro": "x", "hardware": [], "checklist": []},
            "hazard": [
                {
                    "id": "H01",
                    "title": "t",
                    "group": "g",
                    "hazard": "h",
                    "situation": "s",
                    "event": "e",
                    "harm": "x",
                    "before": {"severity": 4, "likelihood": 3},
                    "after": {"severity": 4, "likelihood": 1},
                    "residual": "r",
                    "software": software,
                    "measure": [{"level": level, "text": "m", "tests": tests}],
                }
            ],
        }
    )


TEST = "tests/test_x.py::test_y"


def test_a_hazard_without_a_test_is_drift() -> None:
    found = problems(tiny_log([]), Suite(frozenset(), {}))
    assert any("has no test" in p for p in found), found


def test_a_named_test_that_is_gone_is_drift() -> None:
    found = problems(tiny_log([TEST]), Suite(frozenset(), {}))
    assert found == ["H01: tests/test_x.py::test_y does not exist"]


def test_a_marked_test_the_table_does_not_name_is_drift() -> None:
    other = "tests/test_x.py::test_z"
    suite = Suite(frozenset({TEST, other}), {TEST: frozenset({"H01"}), other: frozenset({"H01"})})
    found = problems(tiny_log([TEST]), suite)
    assert found == [f"{other} is marked for H01, but H01 does not name it"]
    named_unmarked = problems(tiny_log([TEST]), Suite(frozenset({TEST}), {}))
    assert any("is named but not marked" in p for p in named_unmarked), named_unmarked


def test_a_page_that_differs_from_the_render_is_drift(tmp_path: Path) -> None:
    log = tiny_log([TEST])
    results = Results(
        run="2026-12-07 08:00 UTC", tests={TEST: RunResult(outcome="passed", at="2026-12-07")}
    )
    page = render(log, results, "")
    assert "`tests/test_x.py::test_y` (passed 2026-12-07)" in page
    failed = Results(run=results.run, tests={TEST: RunResult(outcome="failed", at="2026-12-07")})
    assert render(log, failed, "") != page  # a new result is a new page
    assert problems(log, Suite(frozenset({TEST}), {TEST: frozenset({"H01"})})) == []


def test_a_hardware_only_hazard_is_said_as_such() -> None:
    page = render(tiny_log([], software=False), Results(), "")
    assert "## What no software measure covers" in page and "**[H01](#h01-t) t**" in page


def test_the_marker_scan_reads_function_class_and_module_marks(tmp_path: Path) -> None:
    (tmp_path / "test_m.py").write_text(
        textwrap.dedent(
            """
            import pytest
            pytestmark = [pytest.mark.integration, pytest.mark.hazard("H02")]

            @pytest.mark.hazard("H01", "H03")
            def test_a(): ...

            class TestB:
                @pytest.mark.hazard("H04")
                def test_c(self): ...
            """
        )
    )
    suite = scan(tmp_path)
    where = f"{tmp_path.name}/test_m.py"
    assert suite.tests == {f"{where}::test_a", f"{where}::TestB::test_c"}
    marks = {k.rsplit("::", 1)[-1]: v for k, v in suite.marked.items()}
    assert marks == {"test_a": {"H01", "H02", "H03"}, "test_c": {"H02", "H04"}}


BENCH = """
<!-- bench:freeze -->
Measured 2026-12-02 05:46 UTC with `python -m bench.freeze` in 991 s.

**From the freeze to every relay off**

| freeze | host | p99 ms |
|---|--:|--:|
| sigstop | quiet | 99.6 |
| sigstop | 2 burners | 103.5 |
<!-- /bench:freeze -->
"""


def test_a_figure_is_read_from_its_cell_and_marked_stale_when_its_bench_changed() -> None:
    f = Figure(
        section="freeze",
        table="From the freeze",
        row=["sigstop", "2 burners"],
        column="p99 ms",
        label="relays off, p99",
        unit=" ms",
    )
    assert figure_value(BENCH, f) == "103.5"
    with pytest.raises(ValueError, match="no row"):
        figure_value(BENCH, f.model_copy(update={"row": ["gil"]}))
    fresh = Results(
        benches={"freeze": BenchStamp(sha=script_sha("freeze"), measured="2026-12-02 05:46 UTC")}
    )
    assert figure(f, fresh, BENCH).endswith("(`bench.freeze`, 2026-12-02 05:46 UTC)")
    changed = Results(benches={"freeze": BenchStamp(sha="0" * 16, measured="2026-12-02 05:46 UTC")})
    assert "stale: bench/freeze.py changed since" in figure(f, changed, BENCH)
