"""One clock on the wire (issue 43, reproduction 2): a real daemon, a request as a hand-written or
JavaScript client sends it (JSON, through a bare Zenoh session).

A `timecode` in milliseconds from 30 s ago with `valid_for: 5` was read as 1000 times "in the
future", passed the stale check, and the machine homed; one a day ahead passed too. Both are
refused `BAD_TIMECODE` with the reason, and nothing moves.
"""

from __future__ import annotations

import json
import math
import time

import pytest

from ride_machine.schema.codec import Format
from ride_machine.schema.status import MachineState
from tests.integration.support import module_machine, raw_get, states_over
from tests.procs import Daemon

pytestmark = pytest.mark.integration

REPLY_TIMEOUT_S = 10.0


machine = module_machine("timecode")


def home_with(daemon: Daemon, tid: str, timecode: float) -> tuple[dict[str, object], bool]:
    """`cmd/home` as JSON text, as `zenoh get` or a browser Rider sends it: the reply, and
    whether the machine went HOMING."""
    body = json.dumps({"transaction_id": tid, "timecode": timecode, "valid_for": 5})
    with daemon.rider(supervise=False) as r:
        replies = raw_get(r, "cmd/home?format=json", body, Format.JSON, REPLY_TIMEOUT_S)
        assert len(replies) == 1 and replies[0].ok is not None, replies
        reply: dict[str, object] = json.loads(replies[0].ok.payload.to_string())
        # Ten cycles after the reply: a Home taken would show HOMING by then.
        homing = any(s.state is MachineState.HOMING for s in states_over(r, 10))
        if homing:
            r.stop()
    return reply, homing


@pytest.mark.hazard("H28")
@pytest.mark.parametrize(
    ("sent", "says"),
    [
        (lambda: round((time.time() - 30.0) * 1000), "milliseconds"),  # Date.now() of 30 s ago
        (lambda: time.time() + 86_400.0, "ahead of this machine's clock"),
    ],
    ids=["milliseconds-30s-ago", "a-day-ahead"],
)
def test_a_timecode_that_is_no_time_in_seconds_is_refused_and_nothing_moves(
    machine: Daemon, sent: object, says: str
) -> None:
    assert callable(sent)
    reply, homing = home_with(machine, f"clock-{len(says)}", sent())
    assert not homing, "the machine moved on a Home it refused"
    assert reply["success"] is False, reply
    error = reply["error"]
    assert isinstance(error, dict)
    assert error["code"] == "BAD_TIMECODE" and error["path"] == "/timecode", error
    assert says in str(error["message"]) and "nothing moved" in str(error["message"])


@pytest.mark.hazard("H28")
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
def test_a_timecode_that_is_no_number_is_refused_and_nothing_moves(
    machine: Daemon, bad: float
) -> None:
    """Issue 58, point 1: `{"timecode": NaN, "valid_for": 5}` passed both the future and the
    stale check (every comparison with NaN is false) and the ride ran."""
    reply, homing = home_with(machine, f"no-number-{bad}", bad)
    assert not homing, "the machine moved on a timecode that is no number"
    assert reply["success"] is False, reply
    error = reply["error"]
    assert isinstance(error, dict) and error["code"] == "BAD_PAYLOAD", error
    assert error["path"] == "/timecode", error


def test_seconds_from_this_clock_are_taken(machine: Daemon) -> None:
    reply, homing = home_with(machine, "clock-seconds", time.time())
    assert reply["success"] is True and homing, reply
