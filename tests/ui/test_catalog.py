"""What the page is told and must not hard-code: which events are incidents (red)."""

from __future__ import annotations

from ride_machine.rider.ui.catalog import event_tone
from ride_machine.schema.events import CommandEvent, FaultEvent, RiderEvent


def test_a_rider_left_at_rest_is_routine_one_lost_mid_motion_is_an_incident() -> None:
    def rider(kind: str, mid_motion: bool | None) -> RiderEvent:
        return RiderEvent.model_validate(
            {"kind": kind, "rider": "r1", "policy": "pause", "mid_motion": mid_motion}
        )

    assert event_tone(rider("rider_lost", False)) == ""
    assert event_tone(rider("rider_lost", True)) == "fault"
    assert event_tone(rider("rider_lost", None)) == "fault"  # an older machine: cannot tell
    assert event_tone(rider("rider_returned", True)) == ""


def test_faults_are_incidents_commands_are_not_and_unknown_kinds_are_read() -> None:
    assert event_tone(FaultEvent(kind="fault_raised", code="TILT_NOT_FOLLOWING")) == "fault"
    assert event_tone(CommandEvent(command="Home", accepted=True, code="RESP_HOME_ACCEPTED")) == ""
    assert event_tone({"kind": "watchdog_trip"}) == "fault"
    assert event_tone({"kind": "from_the_future"}) == ""
