"""The integration tests' excuse for a loaded host: a scenario is ridden again only when the
machine itself said its scan stalled (tests/integration/support.py), never for anything else."""

from __future__ import annotations

import pytest

from ride_machine.schema.status import Fault, FaultCode, MachineState, Status
from tests.integration.support import (
    HostStalled,
    again_after_stall,
    not_spoiled,
    not_stalled,
    scan_stalled,
)


def faulted(code: FaultCode, message: str, state: MachineState = MachineState.FAULT_HW) -> Status:
    fault = Fault(code=code, message=message)
    return Status(machine_id="m1", state=state, fault=fault, seq=1, cycle=1, time=1.0)


WATCHDOG = faulted(
    FaultCode.WATCHDOG, "scan loop stalled 1304 ms; the watchdog forced the outputs safe"
)
OVERDUE_STALLED = faulted(
    FaultCode.ROTATE_HOME_TIMEOUT,
    "rotate home switch not seen within 0.75 s turning CW (…); the scan stalled 0.300 s"
    " meanwhile, as long as the home switch stays closed (0.042 s)",
)
OVERDUE = faulted(FaultCode.ROTATE_HOME_TIMEOUT, "rotate home switch not seen within 0.75 s")


@pytest.mark.parametrize(
    ("status", "stalled"),
    [
        (WATCHDOG, True),
        (OVERDUE_STALLED, True),
        (OVERDUE, False),
        (faulted(FaultCode.TILT_TIMEOUT, "tilt could not settle"), False),
        (faulted(FaultCode.ESTOP, "the scan stalled", MachineState.FAULT_ESTOP), False),
        (Status(machine_id="m1", state=MachineState.RUNNING, seq=1, cycle=1, time=1.0), False),
    ],
    ids=["watchdog", "overdue-stalled", "overdue", "tilt", "estop", "running"],
)
def test_only_the_machines_own_word_on_a_stall_excuses(status: Status, stalled: bool) -> None:
    assert scan_stalled(status) is stalled
    if stalled:
        with pytest.raises(HostStalled, match="own scan stalled"):
            not_stalled(status)
    else:
        assert not_stalled(status) is status


def test_a_scenario_is_ridden_again_after_a_stall_and_at_most_tries_times() -> None:
    calls: list[int] = []

    def stalls_once() -> str:
        calls.append(1)
        if len(calls) == 1:
            not_stalled(WATCHDOG)
        return "done"

    assert again_after_stall(stalls_once) == "done"
    assert len(calls) == 2

    calls.clear()

    def always_stalls() -> None:
        calls.append(1)
        not_stalled(WATCHDOG)

    with pytest.raises(HostStalled):
        again_after_stall(always_stalls, tries=3)
    assert len(calls) == 3


def test_any_other_failure_fails_at_once() -> None:
    calls: list[int] = []

    def wrong() -> None:
        calls.append(1)
        raise AssertionError("session ended early")

    with pytest.raises(AssertionError, match="ended early"):
        again_after_stall(wrong)
    assert calls == [1]


@pytest.mark.parametrize(
    ("status", "excused"),
    [
        (faulted(FaultCode.CALIBRATION_NOT_REPEATABLE, "0.500 s and 0.564 s"), True),
        (faulted(FaultCode.HOME_EDGE_UNCERTAIN, "3 latches refused"), True),
        (WATCHDOG, True),
        (OVERDUE, False),
        (faulted(FaultCode.CALIBRATION_IMPLAUSIBLE, "a revolution of 9 s"), False),
    ],
    ids=["not-repeatable", "edge-uncertain", "watchdog", "overdue", "implausible"],
)
def test_a_measurement_the_machine_refused_as_spoiled_is_taken_again(
    status: Status, excused: bool
) -> None:
    """Run 92, beside three burners: a rotate calibration's two edge timings disagreed (a stall
    between the cycle's clock and its read) and the machine rightly refused it."""
    if excused:
        with pytest.raises(HostStalled):
            not_spoiled(status)
    else:
        assert not_spoiled(status) is status
