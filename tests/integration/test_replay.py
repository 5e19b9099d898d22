"""At most once per transaction id, across a restart (issue 43, reproduction 3).

A Start answered and run to DONE, the daemon restarted and homed again, the same request (same
`transaction_id`, no timecode) sent again: a second ride started and `done/<tid>` went back to
IN_PROGRESS. The daemon now reads the answers of recent commands back from its event history
as it starts (service/adapters/replay.py): the repeat gets the recorded reply, and nothing moves.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from ride_machine.rider.client import Rider
from ride_machine.schema.commands import Command, ReplyCode, StartRequest
from ride_machine.schema.completion import Outcome
from ride_machine.schema.events import CommandEvent, EventQuery
from ride_machine.schema.status import MachineState
from tests.integration.support import fast_args, prepare, settle, states_over
from tests.procs import Daemon, start_daemon

pytestmark = pytest.mark.integration

TID = "replay-start-1"
HISTORY_WAIT_S = 5.0


def command_events(r: Rider, tid: str, count: int) -> list[CommandEvent]:
    """The `command` events of `tid`, once there are `count` (bounded: the history's process
    writes a moment after the command was answered)."""
    deadline = time.monotonic() + HISTORY_WAIT_S
    while True:
        found = [
            e.details
            for e in r.events(EventQuery(kinds=("command",)))
            if isinstance(e.details, CommandEvent) and e.details.transaction_id == tid
        ]
        if len(found) >= count or time.monotonic() > deadline:
            return found
        time.sleep(0.05)


def machine(tmp: Path) -> Daemon:
    return start_daemon(tmp, extra=fast_args(tmp))


@pytest.mark.hazard("H26", "H43")
def test_a_start_repeated_after_a_restart_gets_its_recorded_answer_and_moves_nothing(
    tmp_path: Path,
) -> None:
    request = StartRequest(transaction_id=TID)  # no timecode: no age is judged
    daemon = machine(tmp_path)
    try:
        with daemon.rider() as r:
            prepare(r)
            first = r.command(Command.START, request)
            assert first.success and first.code is ReplyCode.RESP_START_ACCEPTED
            assert settle(r, first).state is MachineState.DONE
            assert r.done(TID).outcome == Outcome.DONE  # type: ignore[union-attr]
    finally:
        daemon.stop()
    daemon = machine(tmp_path)  # the same data dir
    try:
        with daemon.rider() as r:
            settle(r, r.home())
            revolutions = r.sim("world").revolutions
            again = r.command(Command.START, request)
            seen = states_over(r, 20)
            notice = r.done(TID)
            assert abs(r.sim("world").revolutions - revolutions) < 0.05
            repeats = command_events(r, TID, 2)
    finally:
        daemon.stop()
    assert again.success and again.code is ReplyCode.RESP_START_ACCEPTED, again
    assert again.transaction_id == TID and again.timecode == pytest.approx(first.timecode, abs=0.05)
    assert all(s.state is not MachineState.RUNNING for s in seen), [s.state for s in seen]
    assert notice is not None and notice.outcome == Outcome.DONE, notice
    assert [e.repeat for e in repeats] == [False, True], repeats
