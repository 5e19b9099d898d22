"""`machine demo`: a whole session on the simulator backend, found by name, on a simulated clock."""

from __future__ import annotations

import logging

import pytest

from ride_machine.service.config.model import MachineConfig
from ride_machine.service.demo import run_demo


def test_the_demo_runs_the_default_session_to_done(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="demo"):
        assert run_demo(MachineConfig(), speed=0) == 0
    finished = [r.getMessage() for r in caplog.records if "event=finished" in r.getMessage()]
    assert len(finished) == 1
    assert "state=DONE" in finished[0] and "revolutions_done=3" in finished[0]
    progress = [r.getMessage() for r in caplog.records if "event=progress" in r.getMessage()]
    assert progress and "tilt_deg=" in progress[-1]


def test_the_demo_gives_up_when_the_simulated_time_runs_out() -> None:
    with pytest.raises(TimeoutError, match=r"within 1\.0 simulated seconds"):
        run_demo(MachineConfig(), speed=0, max_sim_s=1.0)
