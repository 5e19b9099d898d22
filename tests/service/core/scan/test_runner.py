"""The real-time runner on simulated time: absolute deadlines, overruns, jitter, failures."""

from __future__ import annotations

import logging
import os
import random
from array import array

import pytest

from ride_machine.schema.commands import Command, Reply, StartRequest
from ride_machine.schema.diag import TimingStats
from ride_machine.schema.status import FaultCode
from ride_machine.service.core.scan.beat import BeatReader, BeatWriter, create_beat_fd
from ride_machine.service.core.scan.runner import MAX_CONSECUTIVE_ERRORS, LoopFailed
from ride_machine.service.core.scan.tasks import PendingCommand
from ride_machine.service.core.scan.timing import SORT_CHUNK, CycleStats, percentiles
from tests.service.core.scan.runner_harness import (
    PERIOD,
    TICK,
    Harness,
    S,
    assert_on_grid,
)


def test_cycles_start_on_absolute_deadlines() -> None:
    h = Harness(300)
    h.run()

    assert len(h.starts) == 300
    # The first scan runs at once (commands need a real input image); then one per period.
    assert h.starts[0] - h.t0 == pytest.approx(0.0, abs=20 * TICK)
    assert [round(o) for o in h.grid_offsets()] == list(range(300))
    assert_on_grid(h)
    assert h.runner.pulse.count == 300
    assert h.stats.cycles == 300
    assert h.stats.overruns == 0
    assert h.stats.missed_cycles == 0
    jitter = h.stats.diag(0.0).jitter
    assert 0 <= jitter.min <= jitter.max < 20 * TICK
    assert h.stats.diag(0.0).execution.last == pytest.approx(0.002, abs=50 * TICK)
    # Between cycles it sleeps (one wait per cycle), it does not spin.
    assert len(h.wake.waits) == 299
    assert all(w == pytest.approx(PERIOD - 0.002, abs=50 * TICK) for w in h.wake.waits)


def test_each_cycle_stamps_its_count_and_its_end_in_the_supervisors_record() -> None:
    """The supervisor watches the end of the last cycle (its hang limit, the output guard);
    its simulated world waits on the count (a scan that has seen the home switch closed)."""
    fd = create_beat_fd()
    writer, reader = BeatWriter(fd), BeatReader(fd)
    try:
        h = Harness(20, beat=writer)
        h.run()
        beat = reader.read()
    finally:
        writer.close()
        reader.close()
        os.close(fd)
    assert beat.cycles == h.runner.pulse.count == 20
    assert beat.beat_ns == int(h.runner.pulse.at * 1e9)


def test_varying_execution_time_does_not_drift_the_schedule() -> None:
    rng = random.Random(7)
    costs = [rng.uniform(0.0, 0.009) for _ in range(500)]
    h = Harness(500, cost=lambda i: costs[i])
    h.run()
    assert_on_grid(h)
    assert round(h.grid_offsets()[-1]) == 499
    assert h.stats.overruns == 0
    assert h.stats.diag(0.0).execution.max == pytest.approx(max(costs), abs=50 * TICK)


@pytest.mark.parametrize(
    ("cost_periods", "missed"), [(1.2, 1), (3.5, 3), (10.0, 10)], ids=["1.2", "3.5", "10"]
)
def test_overrun_is_counted_and_missed_cycles_are_skipped(cost_periods: float, missed: int) -> None:
    long = 5
    h = Harness(20, cost=lambda i: cost_periods * PERIOD if i == long else 0.001)
    h.run()

    assert h.stats.overruns == 1
    assert h.stats.missed_cycles == missed
    slots = [round(o) for o in h.grid_offsets()]
    # No burst: the cycles whose deadlines passed during the long one never run...
    assert slots[long + 1] - slots[long] == missed + 1
    # ...the next cycle starts on the next future deadline, and the grid is kept.
    assert h.starts[long + 1] >= h.ends[long]
    assert h.starts[long + 1] - h.ends[long] < PERIOD
    assert_on_grid(h)
    assert slots == sorted(set(slots))
    assert h.stats.diag(0.0).execution.max == pytest.approx(cost_periods * PERIOD, abs=50 * TICK)
    h.stats.reset(h.clock())
    assert h.stats.overruns == 0
    assert h.stats.missed_cycles == 0
    assert h.stats.cycles == 20  # the cycle count is not a resettable counter


def test_repeated_overruns_accumulate() -> None:
    h = Harness(40, cost=lambda i: 0.025 if i % 10 == 3 else 0.001)
    h.run()
    assert h.stats.overruns == 4
    assert h.stats.missed_cycles == 8
    assert h.stats.diag(h.clock()).overruns == 4


def test_late_wakeups_are_recorded_as_jitter() -> None:
    h = Harness(100, oversleep=0.0003)
    h.run()
    jitter = h.stats.diag(0.0).jitter
    assert jitter.min < 20 * TICK  # the first scan runs at once, without a wait
    assert jitter.p50 == pytest.approx(0.0003, abs=20 * TICK)
    assert jitter.max == pytest.approx(0.0003, abs=20 * TICK)
    assert h.stats.overruns == 0


def test_spinning_the_last_stretch_absorbs_late_wakeups() -> None:
    h = Harness(100, oversleep=0.0003, spin_s=0.0005)
    h.run()
    assert h.stats.diag(0.0).jitter.max < 20 * TICK
    assert all(w == pytest.approx(PERIOD - 0.002 - 0.0005, abs=50 * TICK) for w in h.wake.waits)


def test_a_command_is_answered_when_it_arrives_not_at_the_next_deadline() -> None:
    h = Harness(30, homed=True)
    replies: list[Reply] = []
    inbox = h.rig.loop.inbox
    arrive = h.clock.t + 5 * PERIOD + 0.0043

    def put() -> None:
        inbox.put(
            PendingCommand(Command.START, StartRequest(transaction_id="rt-1"), replies.append)
        )

    h.wake.arrivals.append((arrive, put))
    h.run()

    assert len(replies) == 1
    assert replies[0].success
    answered = replies[0].timecode
    assert answered == pytest.approx(arrive, abs=20 * TICK)
    # Between two cycles, more than half a period before the next one would have seen it.
    after = next(i for i, start in enumerate(h.starts) if start > answered)
    assert h.starts[after - 1] < answered
    assert h.starts[after] - answered > PERIOD / 2
    # Motion begins at the next cycle boundary: that cycle is the first to write a relay on.
    assert h.seen[after] == (S.RUNNING, False)
    assert h.seen[after + 1] == (S.RUNNING, True)
    assert_on_grid(h)  # the early wake did not shift the schedule
    assert h.rig.state is S.RUNNING


def test_stop_wakes_a_waiting_runner_at_once() -> None:
    h = Harness(1000)
    stop_at = h.clock.t + 3 * PERIOD + 0.004
    h.wake.arrivals.append((stop_at, h.runner.stop))
    h.run()
    assert len(h.starts) == 4  # at 0, 1, 2 and 3 periods
    assert h.clock.t == pytest.approx(stop_at, abs=20 * TICK)


@pytest.mark.hazard("H04")
def test_shutdown_leaves_outputs_safe() -> None:
    h = Harness(50, running=True)
    h.run()
    assert all(on for _, on in h.seen)  # it was driving the whole time
    assert not h.rig.relays_on()


@pytest.mark.hazard("H03")
@pytest.mark.parametrize("after_step", [False, True], ids=["before-write", "after-write"])
def test_exception_in_a_cycle_forces_outputs_safe_and_faults(
    after_step: bool, caplog: pytest.LogCaptureFixture
) -> None:
    h = Harness(30, running=True, fail=lambda i: i == 10, fail_after_step=after_step)
    with caplog.at_level(logging.ERROR, logger="ride_machine.service.core.scan.runner"):
        h.run()

    assert h.seen[10] == (S.RUNNING, True)
    state, relays = h.seen[11]  # what the failed cycle left behind
    assert state is S.FAULT_HW
    assert not relays
    fault = h.rig.state_machine.fault
    assert fault is not None
    assert fault.code is FaultCode.LOOP_EXCEPTION
    assert "injected failure" in fault.message
    assert h.runner.errors == 1
    assert len(h.starts) == 30  # it kept cycling, safely
    assert all(not on for _, on in h.seen[11:])
    assert not h.rig.relays_on()
    assert len([r for r in caplog.records if "loop_exception" in r.getMessage()]) == 1
    assert_on_grid(h)


@pytest.mark.hazard("H03")
def test_repeated_failures_raise_loop_failed_with_outputs_safe() -> None:
    h = Harness(10_000, running=True, fail=lambda i: i >= 3, fail_after_step=True)
    with pytest.raises(LoopFailed, match="failed 50 cycles in a row"):
        h.run()
    assert h.runner.errors == MAX_CONSECUTIVE_ERRORS
    assert len(h.starts) == 3 + MAX_CONSECUTIVE_ERRORS
    assert not h.rig.relays_on()
    assert not any(h.rig.loop.image.outputs.ro.values())
    assert h.rig.state is S.FAULT_HW


def test_intermittent_failures_never_stop_the_loop() -> None:
    h = Harness(3 * MAX_CONSECUTIVE_ERRORS, fail=lambda i: i % 2 == 0)
    h.run()
    assert h.runner.errors == 3 * MAX_CONSECUTIVE_ERRORS // 2
    assert len(h.starts) == 3 * MAX_CONSECUTIVE_ERRORS
    assert h.rig.state is S.FAULT_HW


def test_cycle_stats_percentiles_and_window() -> None:
    stats = CycleStats(PERIOD, window=10)
    for i in range(1, 21):
        stats.record(i * 1e-5, i * 1e-4, 0)
    diag = stats.diag(5.0)
    assert diag.cycles == 20
    assert diag.window == 10
    assert diag.execution.min == pytest.approx(1e-4)
    assert diag.execution.max == pytest.approx(20e-4)
    assert diag.execution.mean == pytest.approx(10.5e-4)
    assert diag.execution.last == pytest.approx(20e-4)
    # Percentiles over the last 10 samples only (11..20).
    assert diag.execution.p50 in (pytest.approx(15e-4), pytest.approx(16e-4))
    assert diag.execution.p99 == pytest.approx(20e-4)
    assert diag.jitter.max == pytest.approx(20e-5)
    assert diag.period_s == PERIOD
    assert diag.time == 5.0
    assert CycleStats(PERIOD).diag(0.0).execution.max == 0.0


@pytest.mark.parametrize("chunk", [1, 2, 7, 64, SORT_CHUNK])
def test_percentiles_from_sorted_chunks_are_those_of_one_sort(chunk: int) -> None:
    """A large window's percentiles are picked from chunks sorted one at a time (no long GIL
    hold in the `diag` publisher): the same values one full sort gives, with repeats, ties
    across chunks and every size up to a few chunks."""
    rng = random.Random(7)
    qs = (0.0, 0.01, 0.25, 0.5, 0.9, 0.99, 1.0)
    for n in [*range(1, 40), 129, 500, 2 * SORT_CHUNK + 3]:
        for spread in (3, 1000):  # many repeats, then few
            values = array("d", (rng.randrange(spread) * 1e-6 for _ in range(n)))
            full = sorted(values)
            want = [full[min(n - 1, max(0, round(q * (n - 1))))] for q in qs]
            assert percentiles(values, qs, chunk) == want, (n, spread)


def test_cycle_stats_keep_the_series_apart_across_wraps_and_resets() -> None:
    stats = CycleStats(PERIOD, window=4)
    for i in range(1, 8):  # 7 cycles in a ring of 4: wrapped once, mid-lap now
        stats.record(i * 1e-5, i * 1e-3, 1 if i % 3 == 0 else 0)
    d = stats.diag(1.0)
    assert d.window == 4
    assert (d.jitter.last, d.execution.last) == (pytest.approx(7e-5), pytest.approx(7e-3))
    assert (d.jitter.p50, d.execution.p50) == (pytest.approx(6e-5), pytest.approx(6e-3))
    assert (d.jitter.p99, d.execution.p99) == (pytest.approx(7e-5), pytest.approx(7e-3))
    assert (d.jitter.min, d.execution.min) == (pytest.approx(1e-5), pytest.approx(1e-3))
    assert (d.jitter.mean, d.execution.mean) == (pytest.approx(4e-5), pytest.approx(4e-3))
    assert (d.overruns, d.missed_cycles, stats.overruns, stats.missed_cycles) == (2, 2, 2, 2)
    stats.reset(2.0)
    d = stats.diag(3.0)
    assert (d.cycles, d.overruns, d.missed_cycles, d.window, d.since) == (7, 0, 0, 0, 2.0)
    assert d.execution == d.jitter == TimingStats()
    stats.record(3e-5, 2e-3, 0)
    d = stats.diag(4.0)
    assert (d.jitter.last, d.execution.max, d.execution.p50, d.window) == (3e-5, 2e-3, 2e-3, 1)
