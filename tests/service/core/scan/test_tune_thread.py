"""Real-time tuning of the scan thread: what `tune_thread` applies, to the calling thread only."""

from __future__ import annotations

import gc
import sys
import threading
from collections.abc import Callable

import pytest

from ride_machine.service.core.scan.tuning import (
    TIMER_SLACK_NS,
    gc_threshold,
    switch_interval,
    timer_slack,
    tune_thread,
)

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux")


def _slack() -> int:
    """The calling thread's timer slack in ns, as the kernel reports it."""
    slack = timer_slack()
    assert slack is not None
    return slack


def _in_thread(fn: Callable[[], list[str]]) -> tuple[list[str], int]:
    """Run `tune_thread` on a fresh thread; return what it applied and that thread's slack."""
    out: list[tuple[list[str], int]] = []

    def body() -> None:
        applied = fn()
        out.append((applied, _slack()))

    t = threading.Thread(target=body)
    t.start()
    t.join(10.0)
    return out[0]


@linux_only
def test_scan_thread_gets_a_fine_timer_slack() -> None:
    applied, slack = _in_thread(lambda: tune_thread(False, None, None))
    assert slack == TIMER_SLACK_NS
    assert f"timer_slack={TIMER_SLACK_NS}ns" in applied


@linux_only
def test_timer_slack_stays_with_the_thread_that_asked() -> None:
    before = _slack()
    _in_thread(lambda: tune_thread(False, None, None))
    assert _slack() == before != TIMER_SLACK_NS


@linux_only
def test_timer_slack_can_be_left_to_the_kernel() -> None:
    applied, slack = _in_thread(lambda: tune_thread(False, None, None, timer_slack_ns=None))
    assert not any(a.startswith("timer_slack") for a in applied)
    assert slack != TIMER_SLACK_NS


def test_the_switch_interval_is_set_for_the_process() -> None:
    before = sys.getswitchinterval()
    try:
        assert switch_interval(0.0005) == "switch_interval=0.0005s"
        assert sys.getswitchinterval() == pytest.approx(0.0005)
    finally:
        sys.setswitchinterval(before)


def test_the_young_generation_threshold_is_set_and_the_older_ones_kept() -> None:
    before = gc.get_threshold()
    try:
        gc.set_threshold(700, 11, 12)
        assert gc_threshold(10_000) == "gc_threshold=10000"
        assert gc.get_threshold() == (10_000, 11, 12)
    finally:
        gc.set_threshold(*before)
