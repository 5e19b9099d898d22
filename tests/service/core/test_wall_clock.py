"""The machine's wall time against the host's clock: a clock set while the daemon runs is followed
and recorded; one that drifts is followed without a word; one never set is never followed."""

from __future__ import annotations

import logging

import pytest

from ride_machine.schema.commands import Command, Reply, StartRequest
from ride_machine.schema.events import ClockEvent
from ride_machine.service.core.history.events import ListEventSink
from ride_machine.service.core.scan.tasks import PendingCommand
from tests.service.core.scan.runner_harness import (
    PERIOD,
    Harness,
    TickingClock,
    assert_on_grid,
)


@pytest.mark.hazard("H46")
def test_the_machines_wall_time_follows_the_host_clock_when_it_is_set(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A Revolution Pi has no battery clock: NTP sets the host's clock after the daemon started
    (CI saw a resumed virtual machine do the same, 11.6 s). A Rider sends the timecode of the
    set clock; measured against the clock the daemon started with, its Start was refused
    BAD_TIMECODE (11.6 s ahead) until a restart, and every event and status carried the old
    time."""
    step_at, step = 0.1, 11.6
    clock: list[TickingClock] = []

    def wall() -> float:  # the host's clock: the rig's wall time (offset 0), set at `step_at`
        t = clock[0].t
        return t + (step if t - start >= step_at else 0.0)

    h = Harness(40, homed=True, wall=wall)
    clock.append(h.clock)
    start = h.clock.t
    sink = ListEventSink()
    h.rig.loop.recorder.sink = sink
    replies: list[Reply] = []

    def put() -> None:  # sent with the host's clock, as a Rider on it does
        request = StartRequest(transaction_id="clock-1", timecode=wall(), valid_for=5.0)
        h.rig.loop.inbox.put(PendingCommand(Command.START, request, replies.append))

    h.wake.arrivals.append((start + 0.2, put))
    with caplog.at_level(logging.WARNING, logger="machine"):
        h.run()

    assert replies[0].success, replies[0].error
    assert replies[0].request_timecode is not None
    assert replies[0].timecode == pytest.approx(replies[0].request_timecode, abs=1e-3)
    assert h.rig.loop.wall_offset == pytest.approx(step, abs=1e-3)
    status = h.rig.sink.statuses[-1]  # published by a cycle after the Start, on the set clock
    assert start + 0.2 + step <= status.time <= h.clock.t + step
    steps = [(d, t) for d, t, _ in sink.events if isinstance(d, ClockEvent)]
    assert len(steps) == 1, steps  # one step, recorded once, at the cycle that saw it
    assert steps[0][0].step_s == pytest.approx(step, abs=1e-3)
    assert steps[0][1] - start == pytest.approx(step_at + step, abs=PERIOD + 1e-3)
    assert [r.getMessage() for r in caplog.records if "clock_set" in r.getMessage()] == [
        "event=clock_set step_s=11.600"
    ]
    assert_on_grid(h)  # the scan's own clock never moved


@pytest.mark.hazard("H46")
def test_a_wall_clock_that_drifts_is_followed_without_a_clock_set_event(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """This project's test host: its wall clock runs 5 ms a second ahead of its steady clock.
    Wall times follow it, within the 10 ms a change must reach before it is followed; no
    `clock_set` event or line for a drift (there was one every two seconds, drowning the
    history's real events)."""
    h = Harness(1000, wall=lambda: h.clock.t * 1.005 - start * 0.005)
    start = h.clock.t
    sink = ListEventSink()
    h.rig.loop.recorder.sink = sink
    with caplog.at_level(logging.WARNING, logger="machine"):
        h.run()
    drift = (h.clock.t - start) * 0.005
    assert drift > 0.04  # followed several times over the run
    assert h.rig.loop.wall_offset == pytest.approx(drift, abs=0.011)
    assert not [d for d, _, _ in sink.events if isinstance(d, ClockEvent)]
    assert not [r for r in caplog.records if "clock_set" in r.getMessage()]


def test_a_wall_clock_that_is_never_set_is_never_followed() -> None:
    h = Harness(50, wall=lambda: h.clock.t + 0.004)  # 4 ms apart: the reads' noise, no step
    sink = ListEventSink()
    h.rig.loop.recorder.sink = sink
    h.run()
    assert h.rig.loop.wall_offset == 0.0
    assert not [d for d, _, _ in sink.events if isinstance(d, ClockEvent)]
