"""A Rider that left the machine at rest reads as routine, one lost mid-motion as an incident
(`describe`, the text of `rider events` and of the UI's Events panel)."""

from __future__ import annotations

import pytest

from ride_machine.common.event_words import describe
from ride_machine.schema.events import RiderEvent


def lost(**kw: object) -> RiderEvent:
    return RiderEvent.model_validate({"kind": "rider_lost", "rider": "r1", "policy": "pause", **kw})


@pytest.mark.parametrize(
    ("details", "text"),
    [
        (
            lost(mid_motion=False),
            "rider r1 left at rest (nothing moving: policy pause not needed)",
        ),
        (lost(mid_motion=True, acted=True), "rider r1 lost mid-motion: policy pause applied"),
        (
            lost(mid_motion=True),
            "rider r1 lost mid-motion: policy pause, its grace period runs",
        ),
        (
            lost(mid_motion=True, policy="ignore"),
            "rider r1 lost mid-motion: policy ignore, the motion goes on",
        ),
        # From a machine older than `mid_motion`: what it said, nothing guessed.
        (lost(acted=False), "rider r1 lost (policy pause, not applied at once)"),
        (
            RiderEvent(kind="rider_returned", rider="r1", policy="pause", mid_motion=True),
            "rider r1 back (policy pause)",
        ),
    ],
)
def test_a_departure_says_whether_anything_was_moving(details: RiderEvent, text: str) -> None:
    assert describe(details) == text


def test_an_older_reader_keeps_reading_the_new_field_away() -> None:
    """Wire compatibility: the field is added, nothing renamed; old records still load."""
    old = RiderEvent.model_validate_json('{"kind":"rider_lost","rider":"r1","acted":true}')
    assert old.mid_motion is None
    new = lost(mid_motion=False).model_dump(mode="json")
    assert {"rider", "policy", "acted"} <= new.keys() and new["mid_motion"] is False
