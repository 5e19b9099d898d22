"""One config load: file (or defaults), then overrides, then validation: what runs was checked."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from ride_machine.service.cli import load_config, main
from ride_machine.service.config.load import check_candidate, load, load_data
from ride_machine.service.config.model import MachineConfig

# Each bad value fails the same check whether the file or the command line gives it.
BAD = [
    ("/loop/period_s", "[loop]\nperiod_s = 0.1\n", 0.1),  # rotate steps 9° past a 10° arc
    ("/loop/period_s", "[loop]\nperiod_s = 0.0001\n", 0.0001),
    ("/machine/id", '[machine]\nid = "a b"\n', "a b"),
    ("/data_dir", 'data_dir = ""\n', ""),
]


@pytest.mark.parametrize(("pointer", "toml", "value"), BAD)
def test_an_override_meets_the_checks_a_file_value_meets(
    tmp_path: Path, pointer: str, toml: str, value: object
) -> None:
    in_file = tmp_path / "machine.toml"
    in_file.write_text(toml)
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    from_file, file_findings = load(in_file)
    overridden, override_findings = load(empty, {pointer: value})
    assert from_file is None and overridden is None
    assert not override_findings.ok
    assert override_findings == file_findings
    assert pointer in {f.path for f in override_findings.findings}


def test_an_override_replaces_the_file_value_before_the_check(tmp_path: Path) -> None:
    path = tmp_path / "machine.toml"
    path.write_text('data_dir = "here"\n[loop]\nperiod_s = 0.1\n')
    assert load(path)[0] is None
    config, findings = load(path, {"/loop/period_s": 0.005})
    assert findings.ok and config is not None
    assert (config.loop.period_s, config.data_dir) == (0.005, "here")


def test_run_names_the_option_that_gave_a_bad_value() -> None:
    err = io.StringIO()
    assert load_config(None, {"/loop/period_s": 0.1}, stream=err) is None
    assert "--period: error: scan_period at /loop/period_s:" in err.getvalue()


def test_validate_checks_the_overridden_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", "--period", "0.1"]) == 2
    out = capsys.readouterr().out
    assert "/loop/period_s" in out and "the daemon will not start" in out
    assert main(["validate", "--period", "0.005"]) == 0


def test_a_candidate_on_the_bus_is_loaded_like_a_file() -> None:
    running = MachineConfig()
    assert check_candidate(running, None).ok
    toml = check_candidate(running, b"[loop]\nperiod_s = 0.1\n")
    json = check_candidate(running, b'{"loop": {"period_s": 0.1}}')
    assert toml == json == load_data({"loop": {"period_s": 0.1}})[1]
    garbage = check_candidate(running, b"[loop")
    assert not garbage.ok and garbage.findings[0].category == "syntax"


def _nested(depth: int) -> list[object]:
    inner: list[object] = []
    for _ in range(depth):
        inner = [inner]
    return inner


@pytest.mark.parametrize("depth", [600, 990])
def test_config_nested_hundreds_deep_is_one_syntax_finding(depth: int) -> None:
    """A candidate of about a kilobyte: its copy ran out of stack (`RecursionError`)."""
    config, report = load_data({"loop": _nested(depth)})
    assert config is None and not report.ok
    [finding] = report.findings
    assert finding.category == "syntax" and "nested too deeply" in finding.message
