"""A history process that freezes (SIGSTOP; a disk that hangs under it): the daemon notices the
stall, kills it and starts another, no write to its pipe holds a thread for good, and the
safety events it never confirmed are written by the next one or kept by `close`."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from ride_machine.schema.events import EstopEvent, StorageEvent
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters import history, history_ledger, history_spawn
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.history import HistoryProcess
from ride_machine.service.config.model import EventsSection
from tests.service.adapters.eventlog_support import (
    FLUSH_S,
    T0,
    closes_in_time,
    history_processes,
    note,
    page,
    stored_kinds,
)

PRESSED = EstopEvent(kind="estop_pressed", state=MachineState.RUNNING)
RELEASED = EstopEvent(kind="estop_released", state=MachineState.FAULT_ESTOP)
FLOOD = 4000
"""Routine events emitted behind a frozen process: ~700 KB as sent, ten times its pipe."""


class _Said(logging.Handler):
    """Sets `seen` once a log line with `text` is logged."""

    def __init__(self, text: str) -> None:
        super().__init__(logging.ERROR)
        self.text = text
        self.seen = threading.Event()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        line = record.getMessage()
        if self.text in line:
            self.lines.append(line)
            self.seen.set()


def _until(done: Callable[[], bool], timeout: float = FLUSH_S) -> bool:
    """Whether `done()` comes true within `timeout` (asked every 10 ms)."""
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def _freeze_with_an_e_stop_in_its_pipe(log: HistoryProcess) -> subprocess.Popen[bytes]:
    """The process up (one event written), stopped, an E-stop sent down its pipe, then more
    than the pipe holds emitted behind it, and an E-stop release after those."""
    log.emit(note(0.0), T0, 0)
    assert log.flush(FLUSH_S)
    proc = log._proc
    assert proc is not None
    os.kill(proc.pid, signal.SIGSTOP)
    log.emit(PRESSED, T0 + 1, 1)
    assert _until(lambda: log._ledger.sent == 2), "the E-stop never went down the pipe"
    for i in range(FLOOD):
        log.emit(note(float(i)), T0 + 2, 2 + i)
    log.emit(RELEASED, T0 + 3, FLOOD + 2)
    return proc


@pytest.mark.hazard("H41")
def test_a_stalled_process_is_killed_and_the_next_one_writes_its_e_stop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Frozen with an E-stop in its pipe and the pipe full: the daemon's writer thread used to
    wait on it for good, and every event after was dropped. Now the stall is logged, the
    process killed and replaced, and the E-stop it never confirmed written by the next one."""
    monkeypatch.setattr(history_ledger, "STALL_S", 0.5)
    monkeypatch.setattr(history_spawn, "RESPAWN_S", 0.05)
    said = _Said("event=events_process_stalled")
    logging.getLogger(history.__name__).addHandler(said)
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection(queue_capacity=8192))
    log.start()
    frozen: subprocess.Popen[bytes] | None = None
    try:
        frozen = _freeze_with_an_e_stop_in_its_pipe(log)
        assert said.seen.wait(FLUSH_S), "the stall was never noticed"
        assert f"pid={frozen.pid} pending=" in said.lines[0]
        assert frozen.wait(FLUSH_S) == -signal.SIGKILL
        assert _until(lambda: log._proc not in (None, frozen)), "no process took its place"
        assert _until(lambda: log.flush(1.0))
        kinds = stored_kinds(log.path)
        assert kinds.count("estop_pressed") == 1 and kinds.count("estop_released") == 1
        assert kinds.index("estop_pressed") < kinds.index("estop_released")
        [failed] = [e.details for e in page(log).events if isinstance(e.details, StorageEvent)]
        assert "stalled and was killed" in failed.error
        assert "stalled" in (log.diag().last_error or "")
    finally:
        logging.getLogger(history.__name__).removeHandler(said)
        if frozen is not None and frozen.poll() is None:
            frozen.kill()
        log.close()


@pytest.mark.hazard("H41")
def test_close_with_a_frozen_process_ends_in_time_and_keeps_its_safety_events(
    tmp_path: Path,
) -> None:
    """The E-stop it never confirmed and the release still queued go to the file the next
    start writes first, with the count of the routine events lost: before, `close` killed
    the process and they were gone."""
    others = set(history_processes())
    path = tmp_path / EVENTS_FILE
    log = HistoryProcess(path, "m1", EventsSection(queue_capacity=8192))
    log.start()
    frozen: subprocess.Popen[bytes] | None = None
    try:
        frozen = _freeze_with_an_e_stop_in_its_pipe(log)
        closes_in_time(log, frozen, others)
    finally:
        if frozen is not None and frozen.poll() is None:
            frozen.kill()
    again = EventLog(path, "m1", EventsSection())
    again.start()
    try:
        assert again.flush(FLUSH_S)
        events = [e.details for e in page(again).events]
    finally:
        again.close()
    kinds = stored_kinds(path)
    assert kinds.count("estop_pressed") == 1 and kinds.count("estop_released") == 1
    [failed] = [d for d in events if isinstance(d, StorageEvent)]
    assert failed.error.startswith("in the previous run") and failed.lost > 0
