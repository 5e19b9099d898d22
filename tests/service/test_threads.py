"""Daemon threads named for the OS (`service/threads.py`)."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pytest

from ride_machine.service.threads import (
    CALLBACK_THREAD,
    OS_NAME_MAX,
    NamedThread,
    TimedThread,
    name_callback_threads,
    name_os_thread,
    os_name,
)

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="names via /proc")


def _comm_seen_by(thread_factory: type[threading.Thread], name: str) -> str:
    seen: list[str] = []

    def read() -> None:
        seen.append(Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip())

    t = thread_factory(target=read, name=name)
    t.start()
    t.join(5.0)
    return seen[0]


@linux_only
def test_a_named_thread_carries_its_name_for_the_os() -> None:
    assert _comm_seen_by(NamedThread, "eventlog") == "eventlog"


@linux_only
def test_a_plain_thread_carries_its_creators_name_which_is_what_this_fixes() -> None:
    assert _comm_seen_by(threading.Thread, "eventlog") != "eventlog"


@linux_only
def test_a_long_name_is_cut_to_what_the_kernel_keeps() -> None:
    assert _comm_seen_by(NamedThread, "calibration-saved") == "calibration-sav"


def test_a_cut_never_splits_a_character() -> None:
    assert os_name("calibration-saved") == b"calibration-sav"
    assert os_name("ä" * 10) == ("ä" * 7).encode()  # 14 bytes: the 8th would need 16
    assert len(os_name("x" * 40)) == OS_NAME_MAX


def test_naming_is_refused_quietly_where_the_os_cannot(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "platform", "darwin")
    assert name_os_thread("eventlog") is False


@linux_only
def test_zenoh_pythons_callback_threads_are_named_from_outside() -> None:
    release = threading.Event()
    plain = threading.Thread(target=release.wait, name="Thread-99 (pyo3-closure)")
    other = threading.Thread(target=release.wait, name="someone-else")
    plain.start()
    other.start()
    try:
        assert name_callback_threads() >= 1
        comm = Path(f"/proc/self/task/{plain.native_id}/comm").read_text().strip()
        untouched = Path(f"/proc/self/task/{other.native_id}/comm").read_text().strip()
    finally:
        release.set()
        plain.join(5.0)
        other.join(5.0)
    assert comm == CALLBACK_THREAD
    assert untouched != CALLBACK_THREAD


class _Looker(TimedThread):
    """Looks once per (long) sleep; counts its looks and whether its loop has ended."""

    def __init__(self, every_s: float) -> None:
        super().__init__("looker")
        self.every_s = every_s
        self.looks = 0
        self.ended = threading.Event()

    def _run(self) -> None:
        while self.sleep(self.every_s):
            self.looks += 1
        self.ended.set()


def test_a_timed_thread_sleeps_between_looks_and_stop_ends_its_sleep_at_once() -> None:
    looker = _Looker(every_s=0.01)
    looker.start()
    deadline = time.monotonic() + 10.0
    while looker.looks < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert looker.looks >= 3  # it wakes after each sleep
    sleeper = _Looker(every_s=60.0)
    sleeper.start()
    sleeper.stop()  # waits at most 2 s: a sleep of 60 s not cut short fails here
    looker.stop()
    assert sleeper.ended.is_set() and looker.ended.is_set()
    assert sleeper.looks == 0
    assert not sleeper.sleep(60.0)  # stopped: returns at once
