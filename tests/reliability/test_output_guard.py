"""A frozen daemon cannot keep a ride moving: under `machine supervise` as the README runs it
(no --zenoh-config, so Zenoh's own 10 s lease), a daemon frozen mid-move by SIGSTOP, by a
thread holding the GIL, or by a system call that never returns has its relays dropped by the
supervisor's output guard at the watchdog limit, is killed once it stays frozen, and is
replaced by a daemon that comes up not home.

On the code before the guard the relays stayed on until the lease ran out (10.3 s), and the
simulated tilt drove to its end of travel. The bound asserted here is loose for a loaded host;
bench/freeze.py measures the time itself (BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from ride_machine.rider.client import Rider
from ride_machine.schema.status import MachineState
from tests.freeze import LIMIT_S, Freeze, ride_and_freeze
from tests.freeze import supervised as supervised_machine
from tests.procs import Daemon

pytestmark = pytest.mark.integration

OFF_BOUND_S = LIMIT_S + 1.0
"""Far below the 10 s lease the relays waited for before; generous for a loaded host."""


@pytest.fixture(scope="module")
def supervised(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Daemon, Rider]]:
    with supervised_machine(tmp_path_factory.mktemp("guard")) as both:
        yield both


@pytest.mark.hazard("H01", "H02", "H47")
@pytest.mark.parametrize("kind", list(Freeze))
def test_a_frozen_daemon_has_its_relays_dropped_at_the_watchdog_limit(
    supervised: tuple[Daemon, Rider], kind: Freeze
) -> None:
    supervisor, rider = supervised
    trips = supervisor.log().count("event=output_guard_trip")
    outcome = ride_and_freeze(supervisor, rider, kind)
    assert outcome.off_s is not None, "the relays stayed on"
    assert outcome.off_s <= OFF_BOUND_S, outcome
    assert outcome.overrun_deg is not None and outcome.overrun_deg < TILT_BOUND_DEG, outcome
    # The frozen daemon was killed and replaced by one that is not home; the supervisor said
    # why in between.
    status = rider.status()
    assert status.state is MachineState.WARNING_NOT_HOME, status
    log = supervisor.log()
    assert "event=daemon_down" in log
    assert "scan loop stopped cycling" in log
    if kind in OWN_RELAYS_HELD:  # the daemon could not drop them: the guard did, and says so
        assert log.count("event=output_guard_trip") > trips, log[-3000:]
    print(f"\n{kind}: relays off {outcome.off_s * 1e3:.1f} ms, tilt +{outcome.overrun_deg:.2f}°")


TILT_BOUND_DEG = 15.0 * OFF_BOUND_S
"""The tilt's travel in `OFF_BOUND_S` at its nominal speed."""


OWN_RELAYS_HELD = (Freeze.SIGSTOP, Freeze.GIL)
"""Freezes in which the daemon's own watchdog thread cannot run either (a blocked system call
releases the GIL: the in-process watchdog may drop the relays before the guard looks)."""
