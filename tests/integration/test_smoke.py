"""The daemon and a Rider as separate processes over tcp/127.0.0.1."""

from __future__ import annotations

from schema.status import MachineState
from tests.procs import Daemon


def test_rider_reads_status_of_a_fresh_daemon(daemon: Daemon) -> None:
    with daemon.rider() as r:
        status = r.status()
    assert status.machine_id == "m1"
    assert status.state is MachineState.WARNING_NEEDS_CALIBRATION
    assert status.estop.active is False
