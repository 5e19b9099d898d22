"""The daemon and a Rider as separate processes over tcp/127.0.0.1."""

from __future__ import annotations

from pathlib import Path

from ride_machine.schema.status import MachineState
from tests.procs import Daemon


def test_rider_reads_status_of_a_fresh_daemon(daemon: Daemon) -> None:
    with daemon.rider() as r:
        status = r.status()
    assert status.machine_id == "m1"
    assert status.state is MachineState.WARNING_NEEDS_CALIBRATION
    assert status.estop.active is False


def test_the_daemons_threads_carry_their_names_for_the_os(daemon: Daemon) -> None:
    """`top -H` and `ps -L` tell the threads apart: each of ours under its own name, the
    Zenoh runtime under its own, none of ours under the name of the thread that started it."""
    with daemon.rider() as r:
        r.check_home()  # a command answered: the event writer has run
    tasks = Path(f"/proc/{daemon.proc.pid}/task")
    main = (tasks / str(daemon.proc.pid) / "comm").read_text().strip()  # the scan thread
    names = [
        (t / "comm").read_text().strip() for t in tasks.iterdir() if t.name != str(daemon.proc.pid)
    ]
    assert {"eventlog", "eventlog-read", "log-writer", "watchdog", "diag"} <= set(names), names
    assert "zenoh-callback" in names  # zenoh-python's own, for the writes' queryables
    assert main not in names, names
