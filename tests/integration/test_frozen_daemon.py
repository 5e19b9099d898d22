"""A daemon frozen (SIGSTOP) while a Rider sends it Home: the Rider reports the timeout, and the
resumed daemon must not home on that command afterwards (the operator was told it failed)."""

from __future__ import annotations

import os
import signal
import time
import uuid
from pathlib import Path

import pytest

from ride_machine.rider.client import MachineTimeout
from ride_machine.schema.commands import Command, CommandRequest
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import CommandEvent, EventQuery
from ride_machine.schema.status import MachineState
from tests.integration.support import write_fast_config
from tests.procs import running_daemon, sigstop

pytestmark = pytest.mark.integration


@pytest.mark.hazard("H27")
def test_a_home_sent_to_a_frozen_daemon_does_not_move_it_when_it_resumes(tmp_path: Path) -> None:
    config = write_fast_config(tmp_path)
    # No clock margin: the Rider and the daemon share this host's clock.
    config.write_text(config.read_text().replace("[bus]\n", "[bus]\nclock_margin_s = 0.0\n"))
    with (
        running_daemon(tmp_path, "m1", extra=["--config", str(config)]) as daemon,
        daemon.rider(timeout=0.5, retries=0, supervise=False) as r,
    ):
        before = r.status().state
        tid = f"frozen-{uuid.uuid4().hex[:8]}"
        # The sender waits 0.5 s and says it waits 0.2 s: it is stale by the time it is read.
        request = CommandRequest(transaction_id=tid, timecode=time.time(), valid_for=0.2)
        sigstop(daemon.proc.pid)
        try:
            with pytest.raises(MachineTimeout):
                r.command(Command.HOME, request)
        finally:
            os.kill(daemon.proc.pid, signal.SIGCONT)
        # The same transaction again: the machine answers with what it did with the first
        # (at most once by id), or judges this copy just as stale.
        again = r.command(Command.HOME, request, check=False, timeout=10.0)
        assert not again.success and again.error is not None
        assert again.error.code is ErrorCode.STALE_REQUEST, again.error
        status = r.status()
        assert status.state is before and status.state is not MachineState.HOMING
        taken = [
            e.details
            for e in r.events(EventQuery(kinds=("command",)))
            if isinstance(e.details, CommandEvent) and e.details.transaction_id == tid
        ]
        assert taken and not any(c.accepted for c in taken)
