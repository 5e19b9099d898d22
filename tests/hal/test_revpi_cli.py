"""`machine run|supervise|validate` with the RevPi backend: every backend problem is a finding
on stderr and exit code 2, never a traceback; validate runs the same check as start-up."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from ride_machine.hal.iomap import IoMap
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.supervision.assembly import DaemonOptions, open_hal
from ride_machine.service.supervision.restarts import SupervisorOptions
from ride_machine.service.supervision.supervisor import Supervisor
from tests.fixtures.revpi import CONFIG_RSC, make_image
from tests.fixtures.revpi.corpus import path
from tests.procs import run_machine

pytest.importorskip("revpimodio2")
ROOT = Path(__file__).parents[2]


def machine(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "HOME": str(cwd)}
    return run_machine(*args, cwd=ROOT, env=env)


def toml(tmp_path: Path, backend: str, configrsc: str, iomap: str = "") -> Path:
    image = make_image(tmp_path)
    conf = tmp_path / "machine.toml"
    conf.write_text(
        f'data_dir = "{tmp_path / "data"}"\n[hal]\nbackend = "{backend}"\n'
        f'[hal.revpi]\nprocimg = "{image}"\nconfigrsc = "{configrsc}"\n'
        + (f"[hal.iomap]\n{iomap}\n" if iomap else "")
    )
    return conf


@pytest.mark.parametrize("command", ["run", "supervise"])
def test_run_and_supervise_report_a_backend_error_as_findings_with_exit_2(
    tmp_path: Path, command: str
) -> None:
    conf = toml(tmp_path, "sim", str(CONFIG_RSC), 'estop = "O_5"')
    done = machine(command, "--hal", "revpi", "--config", str(conf), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert f"{conf}: error: io_type at /hal/iomap/estop: estop must be a digital input" in (
        done.stderr
    )
    assert not (tmp_path / "data").exists()  # refused before anything opened


@pytest.mark.hazard("H48")
@pytest.mark.parametrize(
    ("layout", "line"),
    [
        ("fractional", "error: revpi_layout at /hal/revpi/configrsc"),
        ("past_image", "past the end of the 4096-byte process image"),
        ("gateway", "error: io_missing at /hal/iomap/tiltPosition"),
    ],
)
def test_run_refuses_a_broken_picto_config_with_findings(
    tmp_path: Path, layout: str, line: str
) -> None:
    conf = toml(tmp_path, "revpi", path(layout))
    done = machine("run", "--config", str(conf), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert line in done.stderr
    assert "Traceback" not in done.stderr


def test_validate_with_hal_revpi_checks_the_host_even_if_the_file_says_sim(
    tmp_path: Path,
) -> None:
    conf = toml(tmp_path, "sim", str(CONFIG_RSC), 'tiltPosition = "RevPiStatus"')
    plain = machine("validate", "--config", str(conf), cwd=tmp_path)
    assert plain.returncode == 0, plain.stdout  # the simulator does not read piCtory files
    done = machine("validate", "--hal", "revpi", "--config", str(conf), cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "io_type" in done.stdout and "/hal/iomap/tiltPosition" in done.stdout
    assert "8-bit input byte of module 'core'" in done.stdout
    assert "the daemon will not start" in done.stdout


def test_validate_and_run_print_the_same_findings(tmp_path: Path) -> None:
    conf = toml(tmp_path, "revpi", path("fractional"))
    checked = machine("validate", "--json", "--config", str(conf), cwd=tmp_path)
    run = machine("run", "--config", str(conf), cwd=tmp_path)
    messages = [f["message"] for f in json.loads(checked.stdout)["findings"]]
    assert messages and all(m in run.stderr for m in messages)


def test_open_hal_turns_a_backend_error_into_findings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = MachineConfig().with_overrides(
        hal={
            "backend": "revpi",
            "revpi": {"procimg": str(tmp_path / "absent"), "configrsc": str(CONFIG_RSC)},
        }
    )
    assert open_hal(config) is None
    err = capsys.readouterr().err
    assert "machine: error: revpi_procimg at /hal/revpi/procimg" in err


def test_supervisor_prints_the_same_findings_when_its_hal_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    iomap = IoMap(estop="O_5").model_dump(by_alias=True)
    config = MachineConfig().with_overrides(
        hal={
            "backend": "revpi",
            "iomap": iomap,
            "revpi": {"procimg": make_image(tmp_path), "configrsc": str(CONFIG_RSC)},
        }
    )
    config = config.model_copy(update={"data_dir": str(tmp_path / "data")})
    assert Supervisor(config, DaemonOptions(), SupervisorOptions()).run() == 2
    assert "machine: error: io_type at /hal/iomap/estop" in capsys.readouterr().err
