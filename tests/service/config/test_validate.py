"""The config check: every kind of finding with its exact JSON pointer; the CLI's exit codes."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest

from ride_machine.schema.findings import Finding, Severity
from ride_machine.service.config.load import load
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.config.validate import semantic_findings, validate_data
from tests.procs import run_machine

E, W = Severity.ERROR, Severity.WARNING


def only(data: dict[str, Any]) -> Finding:
    """The single finding `data` produces."""
    _, report = validate_data(data)
    assert len(report.findings) == 1, report.findings
    return report.findings[0]


# (config data, category, severity, JSON pointer, a piece of the message)
CASES: list[tuple[str, dict[str, Any], str, Severity, str, str]] = [
    ("unknown-top", {"bogus": 1}, "unknown_key", E, "/bogus", "unknown key"),
    ("unknown-nested", {"loop": {"perod_s": 0.01}}, "unknown_key", E, "/loop/perod_s", "unknown"),
    ("unknown-iomap", {"hal": {"iomap": {"lamp": "O_9"}}}, "unknown_key", E, "/hal/iomap/lamp", ""),
    ("type-str-float", {"loop": {"period_s": "0.01"}}, "wrong_type", E, "/loop/period_s", "number"),
    ("type-int-bool", {"loop": {"gc_freeze": 1}}, "wrong_type", E, "/loop/gc_freeze", "boolean"),
    ("type-float-int", {"loop": {"cpu": 1.5}}, "wrong_type", E, "/loop/cpu", "integer"),
    ("type-int-str", {"machine": {"id": 7}}, "wrong_type", E, "/machine/id", "string"),
    ("type-section", {"tilt": 3}, "wrong_type", E, "/tilt", ""),
    ("range-high", {"tilt": {"tolerance_deg": 11.0}}, "out_of_range", E, "/tilt/tolerance_deg",
     "10"),
    ("range-zero", {"rotate": {"nominal_speed_dps": 0}}, "out_of_range", E,
     "/rotate/nominal_speed_dps", "greater than 0"),
    ("range-period", {"loop": {"period_s": 0.0005}}, "out_of_range", E, "/loop/period_s", "0.001"),
    ("range-enum", {"rider_loss": {"policy": "halt"}}, "out_of_range", E, "/rider_loss/policy",
     "'pause', 'stop' or 'ignore'"),
    ("range-backend", {"hal": {"backend": "plc"}}, "out_of_range", E, "/hal/backend", "'sim'"),
    ("range-pattern", {"machine": {"id": "m 1"}}, "out_of_range", E, "/machine/id", "pattern"),
    ("range-empty", {"data_dir": ""}, "out_of_range", E, "/data_dir", "at least 1"),
    ("range-inf", {"tilt": {"gain_max_counts_per_deg": float("inf")}}, "out_of_range", E,
     "/tilt/gain_max_counts_per_deg", "finite"),
    ("range-nan", {"loop": {"period_s": float("nan")}}, "out_of_range", E, "/loop/period_s",
     "finite"),
    ("range-min-max", {"tilt": {"min_deg": 30.0, "max_deg": 20.0}}, "out_of_range", E,
     "/tilt/min_deg", "must be below tilt.max_deg"),
    ("range-gain", {"tilt": {"gain_min_counts_per_deg": 600.0}}, "out_of_range", E,
     "/tilt/gain_min_counts_per_deg", "must be below"),
    ("range-zero", {"tilt": {"zero_min_counts": 1300.0}}, "out_of_range", E,
     "/tilt/zero_min_counts", "must be below"),
    ("calibration-band", {"tilt": {"gain_min_counts_per_deg": 5.0,
                                   "gain_max_counts_per_deg": 500.0}}, "calibration", W,
     "/tilt/gain_min_counts_per_deg", "wider than ±10 %: a calibration off by up to 9900 %"),
    ("calibration-zero", {"tilt": {"zero_min_counts": 1195.0, "zero_max_counts": 1205.0}},
     "calibration", W, "/tilt/zero_min_counts", "less than twice tilt.latch_tolerance_deg"),
    ("io-twice", {"hal": {"iomap": {"tiltDir": "O_1"}}}, "io_conflict", E, "/hal/iomap/tiltDir",
     "'O_1' is already used by 'rotateRelay'"),
    ("io-in-out", {"hal": {"iomap": {"estop": "O_3"}}}, "io_conflict", E, "/hal/iomap/tiltRelay",
     "already used by 'estop'"),
    ("period-python", {"loop": {"period_s": 0.0015}}, "scan_period", W, "/loop/period_s",
     "below the 2 ms"),
    ("period-home-arc", {"loop": {"period_s": 0.06}}, "scan_period", E, "/loop/period_s",
     "more than half the 10° home-switch arc"),
    ("period-tilt-settle", {"tilt": {"tolerance_deg": 0.05}}, "scan_period", E, "/loop/period_s",
     "cannot settle"),
    ("period-tilt-correct", {"tilt": {"tolerance_deg": 0.1}}, "scan_period", W, "/loop/period_s",
     "corrections"),
    ("timeout-revolution", {"rotate": {"revolution_timeout_s": 3.9}}, "timeout", E,
     "/rotate/revolution_timeout_s", "shorter than one revolution at 90°/s (4 s)"),
    ("timeout-revolution-slow", {"rotate": {"revolution_timeout_s": 5.0}}, "timeout", W,
     "/rotate/revolution_timeout_s", "slowest revolution"),
    ("timeout-backoff", {"rotate": {"backoff_timeout_s": 0.1}}, "timeout", E,
     "/rotate/backoff_timeout_s", "10° home arc"),
    ("timeout-tilt-home", {"tilt": {"home_timeout_s": 3.0}}, "timeout", E, "/tilt/home_timeout_s",
     "full tilt travel 0°..60° at 15°/s (4 s)"),
    ("timeout-follow", {"tilt": {"follow_window_s": 0.005, "gain_min_counts_per_deg": 57.0,
                                 "gain_max_counts_per_deg": 63.0},
                        "hal": {"sim": {"ai_gain_counts_per_deg": 60.0}}},
     "timeout", E,
     "/tilt/follow_window_s", "one scan period"),
    ("calibration-stroke", {"tilt": {"calibration_stroke_s": 4.5}}, "calibration", E,
     "/tilt/calibration_stroke_s", "67.5°, beyond the 60° tilt range"),
    ("supervision", {"tilt": {"follow_min_counts": 300}}, "supervision", W,
     "/tilt/follow_min_counts", "may fault a working axis"),
    ("sim-speed", {"hal": {"sim": {"rotate_speed_dps": 200.0}}}, "simulator", W,
     "/hal/sim/rotate_speed_dps", "rotate calibration accepts"),
    ("sim-arc", {"hal": {"sim": {"home_arc_deg": 4.0}}}, "simulator", W, "/hal/sim/home_arc_deg",
     "narrower"),
    ("sim-tilt", {"hal": {"sim": {"tilt_max_deg": 50.0}}}, "simulator", W,
     "/hal/sim/tilt_max_deg", "below tilt.max_deg"),
    ("sim-drive", {"hal": {"sim": {"tilt_speed_dps": 18.0}}}, "simulator", W,
     "/hal/sim/ai_gain_counts_per_deg", "calibrates to 48 counts/°, outside"),
    ("sim-zero", {"hal": {"sim": {"tilt_home_deg": 3.0}}}, "simulator", W,
     "/hal/sim/ai_offset_counts", "reads 1320 counts at its home switch"),
    ("session", {"tilt": {"max_deg": 40.0}}, "session", W, "/tilt/max_deg", "tilts to 45°"),
    ("bus-heartbeat", {"bus": {"heartbeat_s": 0.005}}, "bus", W, "/bus/heartbeat_s",
     "shorter than the scan period"),
    ("bus-diag", {"bus": {"diag_period_s": 0.005}}, "bus", W, "/bus/diag_period_s", ""),
]  # fmt: skip


@pytest.mark.parametrize(
    ("data", "category", "severity", "path", "says"),
    [c[1:] for c in CASES],
    ids=[c[0] for c in CASES],
)
def test_each_kind_of_finding_has_its_json_pointer(
    data: dict[str, Any], category: str, severity: Severity, path: str, says: str
) -> None:
    finding = only(data)
    assert (finding.category, finding.severity, finding.path) == (category, severity, path)
    assert says in finding.message
    config, report = validate_data(data)
    # An error stops the start-up; a warning does not.
    assert report.ok is (severity is W)
    assert (config is not None) is (severity is W)


def test_project_defaults_have_no_findings() -> None:
    config, report = validate_data({})
    assert config == MachineConfig()
    assert report.ok and report.findings == []


@pytest.mark.hazard("H47")
def test_home_arc_check_holds_exactly_at_half_the_arc() -> None:
    base = {"rotate": {"nominal_speed_dps": 100.0, "home_arc_deg": 10.0}}
    ok, _ = validate_data({**base, "loop": {"period_s": 0.05}})  # 5.0° per scan: exactly half
    assert ok is not None
    finding = only({**base, "loop": {"period_s": 0.051}})
    assert finding.path == "/loop/period_s" and "5.1°" in finding.message


@pytest.mark.hazard("H47")
def test_a_watchdog_that_lets_the_rotate_pass_its_arc_is_a_warning() -> None:
    """Run 38: with the tests' 1 s watchdog at 720°/s a stalled scan let the rotate turn two
    revolutions unseen. The defaults (0.1 s at 90°/s: 9° of a 10° arc) hold."""
    finding = only({"loop": {"watchdog_periods": 100}})  # 1 s at 90°/s: 90°
    assert (finding.severity, finding.path) == (W, "/loop/watchdog_periods")
    assert "turn 90° with its relay on, more than its 10° home arc" in finding.message
    config, _ = validate_data({"loop": {"watchdog_periods": 100}})
    assert config is not None  # a warning: the daemon starts


def test_simulator_checks_are_skipped_on_real_hardware() -> None:
    config, report = validate_data(
        {
            "hal": {
                "backend": "revpi",
                "iomap": {"chargePump": "O_5"},
                "sim": {"rotate_speed_dps": 200.0},
            }
        }
    )
    assert config is not None and report.findings == []


@pytest.mark.hazard("H44")
def test_a_revpi_without_a_charge_pump_is_told_what_stops_its_drives() -> None:
    """Issue 53: only the hardware level survives the whole controller stopping."""
    config, report = validate_data({"hal": {"backend": "revpi"}})
    assert config is not None
    (finding,) = report.findings
    assert (finding.category, finding.severity) == ("supervision", "warning")
    assert finding.path == "/hal/iomap/chargePump" and "docs/revpi.md" in finding.message


@pytest.mark.hazard("H44")
def test_a_simulated_charge_pump_relay_the_scan_cannot_hold_is_an_error() -> None:
    pump = {"iomap": {"chargePump": "O_5"}}
    _, short = validate_data({"hal": {**pump, "sim": {"charge_pump_timeout_s": 0.015}}})
    assert [(f.path, f.severity) for f in short.findings] == [
        ("/hal/sim/charge_pump_timeout_s", "error")
    ]
    _, early = validate_data({"hal": {**pump, "sim": {"charge_pump_timeout_s": 0.05}}})
    assert [(f.path, f.severity) for f in early.findings] == [
        ("/hal/sim/charge_pump_timeout_s", "warning")
    ]
    _, clash = validate_data({"hal": {"iomap": {"chargePump": "O_1"}}})
    assert [f.path for f in clash.findings] == ["/hal/iomap/chargePump"]


def test_every_error_is_reported_not_only_the_first() -> None:
    _, report = validate_data(
        {
            "bogus": 1,
            "loop": {"period_s": "fast"},
            "tilt": {"tolerance_deg": -1},
            "hal": {"iomap": {"tiltDir": "O_1"}},
        }
    )
    assert {f.path for f in report.findings} == {
        "/bogus",
        "/loop/period_s",
        "/tilt/tolerance_deg",
        "/hal/iomap/tiltDir",
    }


def test_cross_checks_do_not_repeat_a_bad_value() -> None:
    # The wrong-typed timeout is checked at its default, and its path is reported once.
    _, report = validate_data(
        {
            "rotate": {"nominal_speed_dps": 30.0, "revolution_timeout_s": "20"},
            "hal": {"sim": {"rotate_speed_dps": 30.0}},
        }
    )
    [finding] = report.findings
    assert (finding.category, finding.path) == ("wrong_type", "/rotate/revolution_timeout_s")


def test_not_a_table_is_one_finding() -> None:
    _, report = validate_data([1, 2])  # type: ignore[arg-type]
    [finding] = report.findings
    assert (finding.category, finding.path) == ("wrong_type", "")


def test_iomap_accepts_field_names_too() -> None:
    config, report = validate_data({"hal": {"iomap": {"rotate_home": "I_7"}}})
    assert config is not None and report.findings == []
    assert config.hal.iomap.rotate_home == "I_7"


def _resolve(doc: Any, pointer: str) -> Any:
    for part in pointer.split("/")[1:]:
        doc = doc[part.replace("~1", "/").replace("~0", "~")]
    return doc


@pytest.mark.parametrize(("data", "path"), [(c[1], c[4]) for c in CASES if c[2] != "unknown_key"])
def test_every_finding_path_points_at_a_real_key(data: dict[str, Any], path: str) -> None:
    _resolve(MachineConfig().model_dump(mode="json", by_alias=True), path)


def test_semantic_findings_of_a_valid_model_are_the_same_as_of_its_data() -> None:
    config = MachineConfig().with_overrides(loop={"period_s": 0.0015})
    assert semantic_findings(config) == validate_data({"loop": {"period_s": 0.0015}})[1].findings


# ------------------------------------------------------------------------------ files
def test_missing_file_is_one_finding(tmp_path: Path) -> None:
    config, report = load(tmp_path / "nope.toml")
    assert config is None
    [finding] = report.findings
    assert (finding.category, finding.severity, finding.path) == ("file", E, "")


def test_toml_syntax_error_is_one_finding(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[loop\nperiod_s = 0.01\n")
    _, report = load(path)
    [finding] = report.findings
    assert finding.category == "syntax" and "not valid TOML" in finding.message


def test_toml_specific_values_are_caught(tmp_path: Path) -> None:
    path = tmp_path / "odd.toml"
    path.write_text(
        "[machine]\nid = 1979-05-27\n[tilt]\ngain_max_counts_per_deg = inf\n"
        "[loop]\nperiod_s = nan\n"
    )
    _, report = load(path)
    got = {(f.category, f.path) for f in report.findings}
    assert got == {
        ("wrong_type", "/machine/id"),
        ("out_of_range", "/tilt/gain_max_counts_per_deg"),
        ("out_of_range", "/loop/period_s"),
    }


# ---------------------------------------------------------------- the CLI, as processes
BAD_TOML = """\
data_dir = "data"
[loop]
period_s = 0.06
bogus = true
[rotate]
revolution_timeout_s = "8"
[hal.iomap]
tiltDir = "O_1"
"""
BAD_PATHS = ["/loop/bogus", "/loop/period_s", "/rotate/revolution_timeout_s", "/hal/iomap/tiltDir"]


def machine(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return run_machine(*args, cwd=cwd)


@pytest.fixture
def bad_toml(tmp_path: Path) -> Path:
    path = tmp_path / "bad.toml"
    path.write_text(BAD_TOML)
    return path


@pytest.mark.integration
def test_machine_validate_prints_every_finding_and_exits_2(bad_toml: Path) -> None:
    done = machine("validate", "--config", str(bad_toml), cwd=bad_toml.parent)
    assert done.returncode == 2, done.stderr
    for path in BAD_PATHS:
        assert path in done.stdout
    assert "unknown_key" in done.stdout and "io_conflict" in done.stdout


@pytest.mark.integration
def test_machine_validate_json_lists_the_findings(bad_toml: Path) -> None:
    done = machine("validate", "--json", "--config", str(bad_toml), cwd=bad_toml.parent)
    assert done.returncode == 2
    report = json.loads(done.stdout)
    assert report["ok"] is False
    assert {f["path"] for f in report["findings"]} == set(BAD_PATHS)


@pytest.mark.integration
def test_machine_validate_with_only_warnings_exits_0(tmp_path: Path) -> None:
    path = tmp_path / "warn.toml"
    path.write_text("[loop]\nperiod_s = 0.0015\n")
    done = machine("validate", "--config", str(path), cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "warning" in done.stdout and "/loop/period_s" in done.stdout


@pytest.mark.hazard("H48")
@pytest.mark.integration
def test_daemon_refuses_to_start_on_an_error_and_prints_every_finding(bad_toml: Path) -> None:
    done = machine("run", "--sim", "--config", str(bad_toml), cwd=bad_toml.parent)
    assert done.returncode == 2
    for path in BAD_PATHS:
        assert path in done.stderr
    assert not (bad_toml.parent / "data").exists()  # it never got as far as the data directory


@pytest.mark.integration
def test_machine_validate_checks_the_revpi_io_names(tmp_path: Path) -> None:
    pytest.importorskip("revpimodio2")
    from tests.fixtures.revpi import CONFIG_RSC, make_image

    image = make_image(tmp_path)
    good = tmp_path / "revpi.toml"
    head = (
        f'[hal]\nbackend = "revpi"\n[hal.revpi]\nprocimg = "{image}"\nconfigrsc = "{CONFIG_RSC}"\n'
    )
    good.write_text(head)
    done = machine("validate", "--config", str(good), cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    bad = tmp_path / "revpi-bad.toml"
    bad.write_text(head + '[hal.iomap]\ntiltHome = "I_99"\n')
    done = machine("validate", "--json", "--config", str(bad), cwd=tmp_path)
    assert done.returncode == 2
    paths = {(f["category"], f["path"]) for f in json.loads(done.stdout)["findings"]}
    assert ("io_missing", "/hal/iomap/tiltHome") in paths


def test_findings_carry_seed_000s_structured_extra() -> None:
    _, report = validate_data(
        {
            "loop": {"period_s": -1.0},
            "hal": {"iomap": {"tiltDir": "O_1"}},
            "tilt": {"min_deg": 70.0},
        }
    )
    by_path = {f.path: f for f in report.findings}
    period = by_path["/loop/period_s"]
    assert period.extra["value"] == -1.0 and period.extra["type"] == "greater_than_equal"
    assert isinstance(period.extra["ge"], float | int)  # the limit it broke
    clash = by_path["/hal/iomap/tiltDir"]
    assert clash.extra == {"channel": "O_1", "used_by": "/hal/iomap/rotateRelay"}
    tilt = by_path["/tilt/min_deg"]
    assert tilt.extra["value"] == 70.0 and tilt.extra["lt"] == "/tilt/max_deg"
    _, slow = validate_data({"rotate": {"revolution_timeout_s": 1.0}})
    timeout = next(f for f in slow.findings if f.path == "/rotate/revolution_timeout_s")
    assert timeout.extra["value"] == 1.0 and timeout.extra["other"] == "/rotate/nominal_speed_dps"
    assert isinstance(timeout.extra["ge"], float) and timeout.extra["ge"] > 1.0
    # On the wire (JSON, as seed 000's validate_project answers) `extra` goes along.
    wire = json.loads(report.model_dump_json())
    assert wire["findings"][0]["extra"] == report.findings[0].extra
