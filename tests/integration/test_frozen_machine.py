"""A frozen machine is told the truth about, promptly: `rider status` and `rider io` say within
their timeout that nothing answers (they took 10.4 s, and `io` printed nothing), `rider start
--wait` says the machine is not answering while it waits, and once the machine runs again the
ride ends in the stall it suffered (FAULT_HW WATCHDOG), not in a motion timeout that counted the
frozen time as travel."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.rider.client import MachineTimeout
from ride_machine.schema.status import MachineState
from ride_machine.service.core.storage.persist import CALIBRATION_FILE
from tests.freeze import FREEZE_CONFIG
from tests.integration.support import prepare
from tests.procs import REPO, Daemon, LineReader, rider_cmd, sigstop, start_daemon, stop_process

pytestmark = pytest.mark.integration

TIMEOUT_S = 2.0
SLACK_S = 2.5
"""A process start and a session close on a loaded host; the lease was 10 s."""


@pytest.fixture
def machine(tmp_path: Path) -> Iterator[Daemon]:
    from bench.daemon import calibration_file

    data = tmp_path / "data-m1"
    data.mkdir()
    (data / CALIBRATION_FILE).write_bytes(calibration_file())
    config = tmp_path / "machine.toml"
    config.write_text(FREEZE_CONFIG)
    daemon = start_daemon(tmp_path, extra=["--config", str(config)])
    try:
        yield daemon
    finally:
        os.kill(daemon.proc.pid, signal.SIGCONT)
        daemon.stop()


def cli(daemon: Daemon, *args: str) -> tuple[subprocess.CompletedProcess[str], float]:
    """`rider ARGS` against the daemon's endpoint, no machine named (the README's way)."""
    t0 = time.monotonic()
    done = daemon.run_rider(*args)
    return done, time.monotonic() - t0


@pytest.mark.hazard("H08")
def test_status_and_io_of_a_frozen_machine_are_told_within_the_timeout(machine: Daemon) -> None:
    sigstop(machine.proc.pid)
    t0 = time.monotonic()
    with machine.rider(timeout=TIMEOUT_S) as r, pytest.raises(MachineTimeout) as said:
        r.status()
    assert time.monotonic() - t0 < TIMEOUT_S + SLACK_S
    assert "never answers" in str(said.value) or "did not answer" in str(said.value), said.value
    for what in ("status", "io"):
        done, took = cli(machine, "--timeout", f"{TIMEOUT_S:g}", what)
        assert done.returncode != 0, (what, done.stdout)
        assert "frozen" in done.stderr, (what, done.stderr)
        assert took < TIMEOUT_S + SLACK_S + 1.5, (what, took)  # + the CLI's own start


@pytest.mark.hazard("H02")
def test_wait_says_when_the_machine_goes_silent_and_the_stall_is_the_fault(
    machine: Daemon,
) -> None:
    with machine.rider(timeout=5.0, supervise=False) as r:
        prepare(r)
        cmd = rider_cmd("--connect", machine.endpoint, "--zenoh-config", str(machine.zenoh_config))
        waiting = subprocess.Popen(
            [*cmd, "--machine", "m1", "start", "--wait"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        try:
            r.wait_for({MachineState.RUNNING}, 30.0)
            os.kill(machine.proc.pid, signal.SIGSTOP)
            t_stop = time.monotonic()
            assert waiting.stderr is not None
            lines = LineReader(waiting.stderr)
            said = ""
            while "not answering" not in said:
                line = lines.line(timeout=TIMEOUT_S + 10.0)
                assert line is not None, "the waiting Rider ended"
                said = line
            told_s = time.monotonic() - t_stop
            os.kill(machine.proc.pid, signal.SIGCONT)
            out, err = waiting.communicate(timeout=60)
        finally:
            stop_process(waiting)
    assert waiting.returncode == 1, (out, err)
    assert "FAULT_HW" in out and "WATCHDOG" in out + err, (out, err)
    assert "TILT_TIMEOUT" not in out + err
    assert told_s < 3.0 + TIMEOUT_S + SLACK_S, told_s
