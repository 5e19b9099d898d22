"""The supervisor's `sim/**` work off Zenoh's thread (`PlantRequests`): in order, a plant that
does not answer made NOT_AVAILABLE, a refusal said, a flood refused BUSY, not queued for ever."""

from __future__ import annotations

import functools
import threading
from typing import Any, cast

import pytest

from ride_machine.hal.base import HalError
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.service.bus.request import Request
from ride_machine.service.bus.supervisor import PlantRequests
from ride_machine.service.errors import Busy, MachineError, NotAvailable, Rejected


class Asked:
    """A request as far as the worker sees it: what it was answered or refused with."""

    def __init__(self) -> None:
        self.answered: object = None
        self.refused: MachineError | None = None
        self.done = threading.Event()

    def reply(self, model: object) -> None:
        self.answered = model
        self.done.set()

    def refuse(self, error: MachineError) -> None:
        self.refused = error
        self.done.set()


def test_work_runs_in_order_and_failures_become_refusals() -> None:
    worker = PlantRequests()
    seen: list[int] = []

    def made(i: int) -> Any:
        seen.append(i)
        return i

    try:
        asked = [Asked() for _ in range(5)]
        for i, request in enumerate(asked):
            worker.run(cast(Request, request), functools.partial(made, i))
        gone, bad = Asked(), Asked()

        def plant_gone() -> Any:
            raise HalError("did not answer")

        def bad_payload() -> Any:
            raise Rejected(Error(code=ErrorCode.BAD_PAYLOAD, message="x"))

        worker.run(cast(Request, gone), plant_gone)
        worker.run(cast(Request, bad), bad_payload)
        assert gone.done.wait(5.0) and bad.done.wait(5.0)
        assert seen == [0, 1, 2, 3, 4]
        assert [a.answered for a in asked] == [0, 1, 2, 3, 4]  # each answered with what it made
        assert isinstance(gone.refused, NotAvailable) and "did not answer" in str(gone.refused)
        assert isinstance(bad.refused, Rejected)
    finally:
        worker.close()


def test_a_flood_is_refused_busy_not_queued_without_end() -> None:
    worker = PlantRequests()
    hold = threading.Event()
    try:
        worker.run(cast(Request, Asked()), lambda: cast(Any, hold.wait(5.0)))
        with pytest.raises(Busy):
            for _ in range(PlantRequests.PENDING_MAX + 2):
                worker.run(cast(Request, Asked()), lambda: cast(Any, None))
    finally:
        hold.set()
        worker.close()
