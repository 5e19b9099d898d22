"""Whether this host grants `loop.rt_priority` (service/config/host.py, issue 59): asked of the
kernel, reported by `machine validate` as a warning with how to grant it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ride_machine.service.config.host import fifo_refused
from tests.procs import REPO, machine_cmd

SETPRIV = shutil.which("setpriv") if shutil.which("prlimit") else None


def validate(config: Path, *prefix: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*prefix, *machine_cmd("validate", "--config", str(config), "--json")],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


@pytest.fixture
def config(tmp_path: Path) -> Path:
    path = tmp_path / "machine.toml"
    path.write_text("[loop]\nrt_priority = 50\n")
    return path


def realtime(done: subprocess.CompletedProcess[str]) -> list[dict[str, object]]:
    report = json.loads(done.stdout)
    return [f for f in report["findings"] if f["category"] == "realtime"]


@pytest.mark.skipif(SETPRIV is None, reason="needs setpriv (util-linux) to drop CAP_SYS_NICE")
def test_a_priority_this_process_may_not_use_is_a_warning_with_the_remedy(config: Path) -> None:
    """A process without CAP_SYS_NICE and no rtprio limit (the default of 0): the kernel
    refuses SCHED_FIFO, as in a container that was not granted it."""
    assert SETPRIV is not None
    drop = (SETPRIV, "--bounding-set", "-sys_nice", "--inh-caps", "-sys_nice")
    done = validate(config, *drop, "prlimit", "--rtprio=0")
    assert done.returncode == 0, done.stderr  # a warning: the daemon still starts
    [found] = realtime(done)
    assert found["severity"] == "warning" and found["path"] == "/loop/rt_priority"
    assert "cap_add: [SYS_NICE]" in str(found["message"])
    assert "rtprio" in str(found["message"])


@pytest.mark.skipif(fifo_refused(50) is not None, reason="this host refuses SCHED_FIFO to root")
def test_a_granted_priority_is_no_finding(config: Path) -> None:
    assert realtime(validate(config)) == []


def test_no_priority_asked_is_no_probe(tmp_path: Path) -> None:
    path = tmp_path / "machine.toml"
    path.write_text("[loop]\n")
    assert realtime(validate(path)) == []


def test_the_probe_leaves_the_calling_thread_as_it_was() -> None:
    before = os.sched_getscheduler(0)
    fifo_refused(50)
    assert os.sched_getscheduler(0) == before
    assert sys.getswitchinterval() > 0  # still a normal interpreter
