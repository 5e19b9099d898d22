"""What `--wait` says while it waits (rider/waiting.py): silence once, PAUSED with the
machine's reason, and the point where it gives up (the real link: tests/integration/
test_link_wait.py)."""

from __future__ import annotations

import pytest

from ride_machine.rider.waiting import Silence, WaitTeller, quiet_limit
from ride_machine.schema.status import MachineState, Status


def status(state: MachineState, *warnings: str) -> Status:
    return Status(machine_id="m1", state=state, warnings=list(warnings), seq=1, cycle=1, time=1.0)


def test_paused_is_said_once_with_the_machines_reason(capsys: pytest.CaptureFixture[str]) -> None:
    teller = WaitTeller("m1")
    teller.on_status(status(MachineState.RUNNING))
    teller.on_silence(2.5)
    lost = "controlling Rider lost during RUNNING; policy pause"
    teller.on_status(status(MachineState.PAUSED, lost))
    teller.on_status(status(MachineState.PAUSED, lost))
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3, err
    assert "not answering for 2.5 s (last heard: RUNNING)" in err[0]
    assert "answering again: PAUSED" in err[1]
    assert f"machine PAUSED ({lost})" in err[2]


def test_a_session_without_a_link_says_the_link_is_down(
    capsys: pytest.CaptureFixture[str],
) -> None:
    WaitTeller("m1", link=lambda: "; nothing answers at tcp/127.0.0.1:1").on_silence(3.0)
    assert "the link is down; nothing answers at tcp/127.0.0.1:1" in capsys.readouterr().err


@pytest.mark.hazard("H08")
def test_silence_is_told_once_and_gives_up_past_the_limit() -> None:
    told: list[float] = []
    silence = Silence(2.0, told.append, 6.0, now=100.0)
    assert silence.check(101.0) is None and told == []
    assert silence.check(102.5) is None and told == [2.5]
    assert silence.check(105.0) is None and told == [2.5]
    silence.heard(105.0)
    assert silence.check(110.0) is None and told == [2.5, 5.0]
    assert silence.check(111.5) == 6.5
    assert Silence(2.0, None, None, now=0.0).check(1e6) is None


def test_the_quiet_limit_is_the_timeout_or_slower_heartbeats() -> None:
    assert quiet_limit(2.0, 0.2) == 2.0
    assert quiet_limit(2.0, 1.0) == 2.5
