"""The supervisor's output guard on a fake clock: what it does at a stall, and what it says of
the relays (issue 53: a freeze of the supervisor and the daemon together kept the relays on for
5 s, and the supervisor's log said "outputs off")."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from ride_machine.service.core.scan.beat import BeatReader, BeatWriter, create_beat_fd
from ride_machine.service.supervision.outputguard import GUARD_LATE_S, OutputGuard, Stall

LIMIT_S = 0.1
T0 = 1_000_000_000_000


class Image:
    """The process image's relays as the guard reads and drops them."""

    def __init__(self, on: bool) -> None:
        self.on = on
        self.dropped = 0

    def energised(self) -> bool:
        return self.on

    def force_all_outputs_safe(self) -> None:
        self.on = False
        self.dropped += 1


@pytest.fixture
def record() -> Iterator[tuple[BeatWriter, BeatReader]]:
    fd = create_beat_fd()
    writer, reader = BeatWriter(fd), BeatReader(fd)
    writer.start(LIMIT_S)
    yield writer, reader
    writer.close()
    reader.close()
    os.close(fd)


def guard_on(reader: BeatReader, image: Image) -> tuple[OutputGuard, list[Stall], list[Stall]]:
    trips: list[Stall] = []
    hangs: list[Stall] = []
    guard = OutputGuard(reader, image, on_trip=trips.append, on_hang=hangs.append, hang_s=1.0)
    return guard, trips, hangs


def stall(
    record: tuple[BeatWriter, BeatReader],
    *,
    was_on: bool,
    on_now: bool,
    age_s: float,
    late_s: float = 0.0,
) -> tuple[Image, list[Stall], list[Stall]]:
    """The daemon's last beat (its relays `was_on`), and the guard's look `age_s` later, itself
    `late_s` late, with the relays `on_now` in the image: the image, the trips and the hangs."""
    writer, reader = record
    image = Image(on=on_now)
    guard, trips, hangs = guard_on(reader, image)
    writer.rec.energised = was_on
    writer.rec.beat_ns = T0
    guard.look(reader.read(), T0 + round(age_s * 1e9), late_ns=round(late_s * 1e9))
    return image, trips, hangs


@pytest.mark.hazard("H02")
def test_a_stall_with_a_relay_on_is_made_safe_and_said_so(
    record: tuple[BeatWriter, BeatReader],
) -> None:
    image, trips, _ = stall(record, was_on=True, on_now=True, age_s=0.105)
    assert image.dropped == 1 and trips
    said = trips[0].outputs()
    assert "made safe by the supervisor 0.10 s after" in said and "stopped" not in said


def test_a_stall_off_from_the_last_cycle_on_is_the_only_one_called_off(
    record: tuple[BeatWriter, BeatReader],
) -> None:
    _, trips, hangs = stall(record, was_on=False, on_now=False, age_s=2.0)
    assert not trips and hangs and hangs[0].outputs() == "off"


@pytest.mark.hazard("H04")
def test_relays_found_off_after_a_freeze_that_kept_them_on_are_not_called_off(
    record: tuple[BeatWriter, BeatReader],
) -> None:
    """The supervisor and the daemon stopped together for 5 s, the relays on all along; the
    daemon woke first and dropped them itself, so the guard, stopped as long, reads them off.
    Before, that read was reported as `outputs off`."""
    _, trips, hangs = stall(record, was_on=True, on_now=False, age_s=5.0, late_s=4.9)
    assert not trips and hangs
    said = hangs[0].outputs()
    assert said != "off" and "on for up to 5.00 s" in said
    assert "the supervisor itself was stopped 4.90 s" in said


@pytest.mark.hazard("H04")
def test_a_guard_that_was_stopped_itself_says_so_when_it_makes_safe(
    record: tuple[BeatWriter, BeatReader],
) -> None:
    image, trips, _ = stall(record, was_on=True, on_now=True, age_s=5.0, late_s=2 * GUARD_LATE_S)
    assert image.dropped == 1
    said = trips[0].outputs()
    assert "5.00 s after the daemon's last cycle" in said and "itself was stopped" in said
