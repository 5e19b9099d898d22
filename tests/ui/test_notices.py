"""The UI's completion notices: one that was dropped on the way is asked for, once the status
shows its motion over (a notice is published once; a congested link drops it like any other
update, and a Start then stayed 'accepted' on the page after DONE)."""

from __future__ import annotations

from typing import cast

from ride_machine.rider.client import Rider, UnknownTransaction
from ride_machine.rider.ui.bridge import NOTICE_WAIT_S, Notices
from ride_machine.rider.ui.view import Update
from ride_machine.schema.completion import Completion
from ride_machine.schema.status import MachineState, MotionRef, Status
from tests.schema.completion_samples import done_notice
from tests.ui.test_view import status

notice = done_notice


class Machine:
    """What `Notices` asks of a Rider: `done(transaction_id)`."""

    def __init__(self, *known: str) -> None:
        self.known = set(known)
        self.asked: list[str] = []

    def done(self, transaction: str, timeout: float | None = None) -> Completion | None:
        self.asked.append(transaction)
        if transaction not in self.known:
            raise UnknownTransaction(f"no motion {transaction!r}")
        return notice(transaction)


def moving(t: float, tid: str) -> Status:
    ref = MotionRef(transaction_id=tid, command="Start", started_at=0.0)
    return status(t, MachineState.RUNNING, motion=ref.model_dump())


def test_a_notice_that_never_came_is_asked_for_once_the_motion_is_over() -> None:
    machine, shown = Machine("t1"), list[Update]()
    notices = Notices(cast(Rider, machine), shown.append)
    notices.saw(moving(0.0, "t1"), 0.0)
    notices.saw(status(1.0, MachineState.DONE), 1.0)  # over; its notice lost on the way
    notices.ask_overdue(1.0 + NOTICE_WAIT_S / 2)
    assert machine.asked == []  # it may still come
    notices.ask_overdue(1.0 + NOTICE_WAIT_S)
    assert machine.asked == ["t1"] and shown == [notice("t1")]
    notices.ask_overdue(10.0)
    assert machine.asked == ["t1"]  # once


def test_a_notice_that_came_is_not_asked_for_and_an_unknown_one_is_let_go() -> None:
    machine, shown = Machine(), list[Update]()
    notices = Notices(cast(Rider, machine), shown.append)
    notices.saw(moving(0.0, "t1"), 0.0)
    notices.saw(status(1.0, MachineState.DONE), 1.0)
    notices.saw(notice("t1"), 1.1)  # published after the status, as the machine does
    notices.saw(moving(2.0, "t2"), 2.0)
    notices.saw(status(3.0, MachineState.DONE), 3.0)
    notices.ask_overdue(3.0 + NOTICE_WAIT_S)
    assert machine.asked == ["t2"] and shown == []  # t2 unknown to the machine: nothing shown
    notices.ask_overdue(10.0)
    assert machine.asked == ["t2"]
