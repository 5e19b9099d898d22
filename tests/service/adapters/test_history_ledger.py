"""What the daemon keeps of each history process: what it was sent, what it settled, the safety
events until it confirms them, and when it last made progress."""

from __future__ import annotations

from ride_machine.service.adapters import history_ledger
from ride_machine.service.adapters.history_pipe import MADE
from tests.service.adapters.eventlog_support import T0


def test_the_safety_events_a_process_never_confirmed_are_kept_for_the_next() -> None:
    """Its ledger: a new process is waited for longer; what it settles lets the E-stops it was
    sent go; at its end the rest are the next one's, and only routine events are lost."""
    stall_s, startup_s = history_ledger.STALL_S, history_ledger.STARTUP_S
    ledger = history_ledger.Ledger(0.0)
    first, second = (MADE, "estop_pressed", "{}", T0, 1), (MADE, "estop_released", "{}", T0, 3)
    routine = (MADE, "state", "{}", T0, 2)
    ledger.took([routine, first, routine, second])
    assert not ledger.stalled(startup_s - 1.0, sending=False)
    ledger.said(0, 1.0)  # its first word, nothing settled yet: from now on, `STALL_S`
    assert ledger.stalled(1.0 + stall_s + 0.1, sending=False)
    ledger.said(2, 20.0)  # the first E-stop settled
    assert not ledger.stalled(20.0 + stall_s - 0.1, sending=False)
    assert ledger.unconfirmed() == (1, [second])
    assert not ledger.stalled(100.0, sending=False)  # it owes nothing now
    assert ledger.stalled(100.0, sending=True)  # but a send that waits that long has stalled
