"""What moved nothing is reported as moving nothing (issue 58, reproductions 8 and 9), through a
real daemon and the Rider.

8. `params set tilt.max_deg 50`, then a session asking for 55°: the Start is refused for its
   session, and the old machine dropped both home references though no axis had moved (a Home
   was needed again).
9. `calibration set --tilt-offset <offset + 1300> --tilt-gain 40` on an idle machine: the old
   machine reported the standing tilt at about −321 °/s (its position jumped by the new offset
   in one cycle) until it moved.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from ride_machine.rider.client import Rider
from ride_machine.rider.errors import CommandRefused
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import TiltCalibrationSet
from ride_machine.schema.commands import RotateStep, Session, TiltStep
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MachineState
from tests.integration.support import fast_daemon, prepare

pytestmark = pytest.mark.integration


def tilt_records(rider: Rider, after: int, seconds: float = 1.0) -> list[AxisRecord]:
    """The tilt's records of cycles after `after`, as read for `seconds` (a record at rest is
    published when it changes: here once, as the calibration is entered)."""
    seen: dict[int, AxisRecord] = {}
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline or not seen:
        assert time.monotonic() < deadline + 30.0, "the tilt's record was never published again"
        [tilt] = [a for a in rider.axes() if a.axis == "tilt"]
        if tilt.cycle > after:
            seen[tilt.cycle] = tilt
    return list(seen.values())


@pytest.mark.hazard("H29")
def test_a_start_refused_for_its_session_keeps_both_home_references(tmp_path: Path) -> None:
    with fast_daemon(tmp_path) as daemon, daemon.rider(timeout=5.0) as rider:
        prepare(rider)
        rider.set_param("tilt.max_deg", 50.0)
        steep = Session(name="steep", steps=[TiltStep(degrees=55.0), RotateStep(revolutions=1)])
        with pytest.raises(CommandRefused) as refused:
            rider.start(steep)
        assert refused.value.error.code is ErrorCode.INVALID_SESSION, refused.value
        rider.wait_for([MachineState.FAULT_HW], timeout=10.0)  # the session's fault, as before
        stop = rider.stop()  # clears it
        status = rider.wait_for([MachineState.DONE], timeout=10.0, after=stop.timecode)
        assert status.homed.tilt and status.homed.rotate, status
        # Homed still: a valid session starts without a Home first.
        gentle = Session(name="gentle", steps=[TiltStep(degrees=10.0), RotateStep(revolutions=1)])
        assert rider.start(gentle).success
        rider.stop()


def test_a_calibration_entered_at_rest_reports_the_standing_tilt_at_rest(tmp_path: Path) -> None:
    with fast_daemon(tmp_path) as daemon, daemon.rider(timeout=5.0) as rider:
        prepare(rider)
        assert rider.status().state is MachineState.IDLE
        tilt = rider.calibration().tilt
        assert tilt is not None
        [before] = [a for a in rider.axes() if a.axis == "tilt"]
        offset = tilt.offset_counts + 30  # within the sensor's commissioned scale (±40)
        rider.set_calibration(
            tilt=TiltCalibrationSet(offset_counts=offset, gain_counts_per_deg=40.0)
        )
        records = tilt_records(rider, before.cycle)
    assert all(r.velocity_fb == 0.0 for r in records), [(r.cycle, r.velocity_fb) for r in records]
