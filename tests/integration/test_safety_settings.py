"""Safety settings are not ordinary parameters (issue 43, reproduction 7), with real processes.

`rider params set rider_loss.policy '"ignore"'` was accepted while RUNNING; the supervising
Rider SIGKILLed, the ride ran on to DONE. A write that makes a safety setting less strict than
the config file is refused (`PARAM_LOCKED`), and on the record with who asked; the deadman
pauses the ride.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ride_machine.schema.events import EventQuery, ParamEvent
from ride_machine.schema.status import MachineState
from tests.integration import rider_proc
from tests.integration.support import fast_daemon, relays_off

pytestmark = pytest.mark.integration

LOSS_BOUND_S = 10.0
"""The fast config's heartbeat timeout (1 s) and a loaded host's margin; the session runs
40 revolutions (20 s), so a ride nobody paused would still be RUNNING."""


@pytest.mark.hazard("H06", "H25")
def test_the_deadman_cannot_be_switched_off_during_a_ride(tmp_path: Path) -> None:
    with fast_daemon(tmp_path) as daemon, rider_proc.supervising(daemon) as (victim, _):
        tried = daemon.cli("params", "set", "rider_loss.policy", '"ignore"')
        weaker = daemon.cli("params", "set", "rider_loss.timeout_s", "30")
        with daemon.rider(supervise=False) as observer:
            assert observer.status().state is MachineState.RUNNING
            assert observer.param("rider_loss.policy").value == "pause"
            paused, _ = rider_proc.kill_until_paused(victim, observer, LOSS_BOUND_S)
            assert relays_off(observer)
            record = [
                e.details
                for e in observer.events(EventQuery(kinds=("safety_changed",)))
                if isinstance(e.details, ParamEvent)
            ]
    for done in (tried, weaker):
        assert done.returncode == 1, done.stdout + done.stderr
        assert "PARAM_LOCKED" in done.stderr and "config file" in done.stderr, done.stderr
    assert paused.previous_state is MachineState.RUNNING and not paused.rider_connected
    asked = {(e.name, e.new, e.accepted) for e in record}
    assert asked == {("rider_loss.policy", "ignore", False), ("rider_loss.timeout_s", 30.0, False)}
    assert all(e.by and e.by.startswith("anonymous/") for e in record), record
