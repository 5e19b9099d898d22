"""A stall is told from a danger: a scan that stops with every output off is counted, not a
fault; one that stops with a relay on drops the outputs in the cycle it is seen and ends in
FAULT_HW (WATCHDOG), never in a motion timeout the lost time would otherwise look like.

The runner runs on simulated time (tests/service/core/scan/test_runner.py's harness): a stall
between two cycles is a wait that oversleeps; a stall inside one is a cycle that takes that long.
"""

from __future__ import annotations

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.status import FaultCode, MachineState
from tests.service.core.scan.test_runner import Harness

LIMIT = 0.1
STALL = 0.5
AT = 30
"""The cycle the stall hits (after the watchdog arms)."""


def stalled(where: str, **kwargs: object) -> Harness:
    """A runner on simulated time whose scan stops for `STALL` s at cycle `AT`, `where`
    "between" two cycles (the thread sleeps too long) or "inside" one (it is stuck in it)."""
    if where == "inside":
        h = Harness(60, cost=lambda i: STALL if i == AT else 0.002, stall_limit=LIMIT, **kwargs)  # type: ignore[arg-type]
    else:
        h = Harness(60, stall_limit=LIMIT, **kwargs)  # type: ignore[arg-type]
        at = h.clock.t + (AT - 0.5) * 0.010
        h.wake.arrivals.append((at, lambda: h.clock.advance(STALL)))
    h.run()
    return h


@pytest.mark.hazard("H01")
@pytest.mark.parametrize("where", ["between", "inside"])
def test_a_stall_at_rest_is_counted_and_changes_nothing(where: str) -> None:
    h = stalled(where, homed=True)
    rig = h.rig
    assert rig.state is MachineState.IDLE
    assert rig.state_machine.fault is None
    diag = h.stats.diag(h.clock())
    assert diag.stalls == 1
    assert diag.watchdog_trips == 0
    assert diag.longest_stall_s >= STALL
    assert diag.watchdog_limit_s is None or diag.watchdog_limit_s == LIMIT
    assert not [t for t in rig.transitions if t.new is MachineState.FAULT_HW]


@pytest.mark.hazard("H01", "H47")
@pytest.mark.parametrize("where", ["between", "inside"])
def test_a_stall_while_moving_drops_the_relays_and_is_the_fault_reported(where: str) -> None:
    h = stalled(where, running=True)
    rig = h.rig
    assert rig.state is MachineState.FAULT_HW
    assert rig.state_machine.fault is not None
    assert rig.state_machine.fault.code is FaultCode.WATCHDOG, rig.state_machine.fault
    faults = [t for t in rig.transitions if t.new is MachineState.FAULT_HW]
    assert len(faults) == 1, faults  # the watchdog's, not a tilt timeout after it
    # Relays on up to the stall; off from the cycle that saw it, for good (a stall between
    # cycles is seen before cycle AT runs; one inside cycle AT as that cycle ends).
    state, on = h.seen[AT - 1]
    assert state is MachineState.RUNNING and on
    first_off = AT if where == "between" else AT + 1
    assert not any(relays for _, relays in h.seen[first_off:])
    assert h.seen[AT + 2][0] is MachineState.FAULT_HW
    diag = h.stats.diag(h.clock())
    assert diag.stalls == 1
    assert diag.watchdog_trips == 1


def test_a_stall_after_a_released_estop_keeps_the_estop_latch_and_resume_works() -> None:
    """The README's quick start: E-stop pressed and released (FAULT_ESTOP, latched), then the
    host stalls the idle daemon: still FAULT_ESTOP, so `resume` is accepted."""
    h = stalled("between", homed=True, estopped=True)
    rig = h.rig
    assert rig.state is MachineState.FAULT_ESTOP
    assert h.stats.diag(h.clock()).stalls == 1
    assert rig.send(Command.RESUME).success
    assert rig.state is MachineState.IDLE
