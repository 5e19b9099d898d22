"""The request's `timecode` (the sender's clock, seconds) is echoed in the reply and logged."""

from __future__ import annotations

import logging

import pytest

from ride_machine.schema.commands import Command
from tests.rig import Rig


def test_the_request_timecode_is_echoed_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    rig = Rig()
    sent = (
        rig.clock() + rig.state_machine.wall_offset - 0.375
    )  # the sender's clock, a little behind
    with caplog.at_level(logging.INFO, logger="machine"):
        accepted = rig.send(Command.CALIBRATE_TILT, transaction_id="tc1", timecode=sent)
        refused = rig.send(Command.HOME, transaction_id="tc2", timecode=sent + 0.25)
        bare = rig.send(Command.CHECK_HOME, transaction_id="tc3")
    assert accepted.success and accepted.request_timecode == sent
    assert not refused.success and refused.request_timecode == sent + 0.25
    assert bare.request_timecode is None
    assert accepted.timecode != accepted.request_timecode  # the machine's own clock
    lines = [r.getMessage() for r in caplog.records if "event=command" in r.getMessage()]
    assert "tx=tc1 command=CalibrateTilt" in lines[0] and f"timecode={sent}" in lines[0]
    assert "tx=tc2" in lines[1] and "code=WRONG_STATE" in lines[1]
