"""A daemon whose log reader stops reading (a frozen log collector, a full pipe) keeps scanning
and answering: log lines wait for their writer thread, and none of them is lost."""

from __future__ import annotations

from pathlib import Path

import pytest

from ride_machine.schema.completion import Outcome
from ride_machine.schema.status import MachineState
from tests.procs import LineReader, running_daemon

pytestmark = pytest.mark.integration

COMMANDS = 1500
"""Each logs one ~170-byte line: ~250 KB, four times what a pipe holds unread."""


@pytest.mark.hazard("H42")
def test_a_log_reader_that_stops_reading_never_stalls_the_machine(tmp_path: Path) -> None:
    with running_daemon(tmp_path, "m1", pipe=True) as daemon:
        assert daemon.proc.stdout is not None
        with daemon.rider(timeout=2.0, retries=0, supervise=False) as r:
            before = r.diag()
            for _ in range(COMMANDS):
                r.check_home()  # raises on a timeout: the old logging blocked here
            home = r.home()
            notice = r.wait_done(home, timeout=30.0)
            assert notice.outcome is Outcome.DONE, notice
            after = r.diag()
            assert r.status().state is not MachineState.FAULT_HW
        # The loop kept its cycle while the pipe was full (the watchdog trips at one second).
        assert after.cycles > before.cycles
        # Reading again, every line arrives: one per command, in the order they were sent.
        lines = LineReader(daemon.proc.stdout)
        tids: list[str] = []
        while len(tids) < COMMANDS:
            line = lines.line(timeout=10.0)
            assert line is not None, f"daemon output ended after {len(tids)} command lines"
            assert "event=log_lines_dropped" not in line, line
            if "event=command" in line and "command=CheckHome" in line:
                tids.append(line.split(" tx=", 1)[1].split(" ", 1)[0])
        assert tids == sorted(tids, key=lambda t: int(t.rsplit("-", 1)[1]))
