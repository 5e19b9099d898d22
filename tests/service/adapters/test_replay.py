"""At most once across a restart (service/adapters/replay.py): the answers a daemon gave are
read back from its event history as it starts; the real restart: tests/integration/
test_replay.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from ride_machine.schema.codec import Format, decode
from ride_machine.schema.commands import Reply, ReplyCode
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import CommandEvent, CompletionEvent
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.replay import recall
from ride_machine.service.config.model import EventsSection

T0 = 1_800_000_000.0


def history(path: Path, machine_id: str = "m1") -> EventLog:
    log = EventLog(path, machine_id, EventsSection())
    log.start()
    return log


def command(tid: str, accepted: bool = True, repeat: bool = False) -> CommandEvent:
    return CommandEvent(
        command="Start",
        transaction_id=tid,
        accepted=accepted,
        code="RESP_START_ACCEPTED" if accepted else "NOT_HOME",
        message="" if accepted else "Start refused: rotate not home",
        state=MachineState.RUNNING if accepted else MachineState.WARNING_NOT_HOME,
        repeat=repeat,
    )


def test_answers_and_notices_come_back_oldest_first(tmp_path: Path) -> None:
    path = tmp_path / EVENTS_FILE
    log = history(path)
    log.emit(command("t1"), T0, 1)
    log.emit(command("t2", accepted=False), T0 + 1, 2)
    log.emit(command("t1", repeat=True), T0 + 2, 3)  # a repeat: its first answer counts
    ended = CompletionEvent(
        command="Start", transaction_id="t1", outcome="DONE", state=MachineState.DONE
    )
    log.emit(ended, T0 + 3, 4)
    assert log.flush()
    log.close()
    got = recall(path, "m1", 10)
    assert [(tid, cmd) for tid, cmd, _ in got.replies] == [("t1", "Start"), ("t2", "Start")]
    first, refused = (decode(Reply, packed, Format.MSGPACK) for _, _, packed in got.replies)
    assert first.success and first.code is ReplyCode.RESP_START_ACCEPTED and first.timecode == T0
    assert not refused.success and refused.error is not None
    assert refused.error.code is ErrorCode.NOT_HOME and "not home" in refused.error.message
    (notice,) = got.completions
    assert notice.transaction_id == "t1" and notice.outcome == "DONE"
    assert notice.started_at == T0 and notice.time == T0 + 3
    assert got.since == T0


@pytest.mark.hazard("H26")
def test_the_window_keeps_the_newest_and_another_machine_is_not_recalled(
    tmp_path: Path,
) -> None:
    path = tmp_path / EVENTS_FILE
    log = history(path)
    for i in range(5):
        log.emit(command(f"t{i}"), T0 + i, i)
    assert log.flush()
    log.close()
    assert [tid for tid, _, _ in recall(path, "m1", 2).replies] == ["t3", "t4"]
    assert recall(path, "m2", 10).replies == []


def test_no_history_recalls_nothing(tmp_path: Path) -> None:
    assert recall(tmp_path / EVENTS_FILE, "m1", 10).replies == []
