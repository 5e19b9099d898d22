"""The tests' `Preparation`, on a scripted machine (no process): it rides again only after a fault
the loaded host caused, with the simulated world's count of late steps to show for it.

A supervised session that faulted while the world was late (CI, stop 48: a tilt that moved 8.1°
in 0.24 s because the world stood still) failed a test that was about something else; any other
fault must still fail it.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from ride_machine.schema.commands import Reply, ReplyCode
from ride_machine.schema.status import AxesFlags, Fault, FaultCode, MachineState, Status
from tests.integration.support import Preparation

Outcome = (
    tuple[str, MachineState, FaultCode | None, int]
    | tuple[str, MachineState, FaultCode | None, int, str]
)
"""A command, the state that settles it, its fault, the late steps the world counts then, and
what the fault's message adds to its code."""


class Scripted:
    """Stands for a Rider: each command settles as the script says, in order."""

    def __init__(self, script: list[Outcome]) -> None:
        self.script = iter(script)
        self.calls: list[str] = []
        self.late = 0
        self.now = Status(
            machine_id="m1",
            state=MachineState.IDLE,
            calibrated=AxesFlags(tilt=True, rotate=True),
            seq=0,
            cycle=0,
            time=0.0,
        )

    def command(self, name: str) -> Reply:
        expected, state, code, late, *said = next(self.script)
        assert name == expected, f"{name} where the script has {expected}"
        self.calls.append(name)
        self.late += late
        fault = None if code is None else Fault(code=code, message=code.value + "".join(said))
        self.now = self.now.model_copy(update={"state": state, "fault": fault})
        return Reply(
            transaction_id=None, command=name, timecode=0.0, success=True, code=ReplyCode.RESP_CHECK
        )

    def status(self) -> Status:
        return self.now

    def calibrate_tilt(self) -> Reply:
        return self.command("calibrate_tilt")

    def calibrate_rotate(self) -> Reply:
        return self.command("calibrate_rotate")

    def home(self) -> Reply:
        return self.command("home")

    def wait_for(self, states: object, timeout: float, after: float | None = None) -> Status:
        return self.now

    def sim(self, what: str) -> SimpleNamespace:
        assert what == "world"
        return SimpleNamespace(late_steps=self.late)


def ride(machine: Scripted) -> Status:
    ready = Preparation(machine)  # type: ignore[arg-type]  # the Rider's calls it makes, scripted
    _, status = ready.ride(lambda: machine.command("start"), lambda reply: machine.status())
    return status


IDLE, RUNNING, FAULT = MachineState.IDLE, MachineState.RUNNING, MachineState.FAULT_HW


def test_a_session_that_faulted_while_the_world_was_late_calibrates_the_tilt_and_rides_again() -> (
    None
):
    machine = Scripted(
        [
            ("home", IDLE, None, 0),
            ("start", FAULT, FaultCode.TILT_SPEED_IMPLAUSIBLE, 1),
            ("calibrate_tilt", IDLE, None, 0),
            ("home", IDLE, None, 0),
            ("start", RUNNING, None, 0),
        ]
    )
    assert ride(machine).state is RUNNING
    assert machine.calls == ["home", "start", "calibrate_tilt", "home", "start"]


@pytest.mark.parametrize(("said", "late"), [("; the scan stalled 0.300 s meanwhile", 0), ("", 1)])
def test_a_home_edge_a_stall_hid_homes_and_rides_again(said: str, late: int) -> None:
    """Run 46: the supervised ride faulted ROTATE_HOME_TIMEOUT; the daemon names its own stall,
    the world counts its own lateness; either lets the ride go again (no new calibration)."""
    machine = Scripted(
        [
            ("home", IDLE, None, 0),
            ("start", FAULT, FaultCode.ROTATE_HOME_TIMEOUT, late, said),
            ("home", IDLE, None, 0),
            ("start", RUNNING, None, 0),
        ]
    )
    assert ride(machine).state is RUNNING
    assert machine.calls == ["home", "start", "home", "start"]


def test_a_watchdog_trip_homes_and_rides_again() -> None:
    """CI, stop 50: a loaded host froze a test daemon for over its 1 s watchdog limit mid-ride;
    the machine rightly went FAULT_HW (WATCHDOG), its own measure of the stall."""
    machine = Scripted(
        [
            ("home", IDLE, None, 0),
            ("start", FAULT, FaultCode.WATCHDOG, 0),
            ("home", IDLE, None, 0),
            ("start", RUNNING, None, 0),
        ]
    )
    assert ride(machine).state is RUNNING
    assert machine.calls == ["home", "start", "home", "start"]


@pytest.mark.parametrize(
    ("code", "late", "said"),
    [
        (FaultCode.TILT_SPEED_IMPLAUSIBLE, 0, "the simulated world was never late"),
        (FaultCode.ROTATE_HOME_TIMEOUT, 0, "neither the scan nor the world stalled"),
        (FaultCode.ROTATE_SPEED_IMPLAUSIBLE, 1, "ROTATE_SPEED_IMPLAUSIBLE"),
    ],
)
def test_any_other_fault_of_a_session_fails_the_test(code: FaultCode, late: int, said: str) -> None:
    machine = Scripted([("home", IDLE, None, 0), ("start", FAULT, code, late)])
    with pytest.raises(AssertionError, match=said):
        ride(machine)
    assert machine.calls == ["home", "start"]


def test_a_world_late_in_every_ride_gives_up_after_the_tries() -> None:
    late_ride = [
        ("calibrate_tilt", IDLE, None, 0),
        ("home", IDLE, None, 0),
        ("start", FAULT, FaultCode.TILT_NOT_FOLLOWING, 1),
    ]
    machine = Scripted(late_ride[1:] + late_ride + late_ride)
    with pytest.raises(AssertionError, match="late in 3 rides in a row"):
        ride(machine)
    assert machine.calls.count("start") == 3
