"""The event history in a process of its own: what only `HistoryProcess` does.

What it shares with the in-thread `EventLog` (order, seq, listeners, drops, retention, set-aside
files, a full disk) is tested on both in tests/service/adapters/test_eventlog.py; a process that
freezes, in tests/service/adapters/test_history_stall.py.
"""

from __future__ import annotations

import logging
import os
import signal
import sqlite3
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.schema.events import (
    CommandEvent,
    DaemonStartEvent,
    DaemonStopEvent,
    EstopEvent,
    EventQuery,
    StorageEvent,
    WatchdogEvent,
)
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters import eventlog, history_spawn
from ride_machine.service.adapters.eventdb import WRITER_WAIT_S, StoredRow, connect
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.eventread import read_page
from ride_machine.service.adapters.history import HistoryProcess
from ride_machine.service.adapters.history_pipe import BATCH, MADE, encode
from ride_machine.service.adapters.history_writer import WriterSettings, _Pipe, _Writer
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.facts import CommandFacts
from ride_machine.service.core.history.held import Held, LogLine
from tests.service.adapters.eventlog_support import (
    FLUSH_S,
    closes_in_time,
    command_tids,
    facts,
    history_processes,
    open_log,
    stored_kinds,
)

T0 = time.time()


@pytest.fixture
def log(tmp_path: Path) -> Iterator[HistoryProcess]:
    events = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection())
    events.start()
    yield events
    events.close()


def stored(log: HistoryProcess) -> list[object]:
    with connect(log.path) as conn:
        return [e.details for e in read_page(conn, "m1", EventQuery(), 500).events]


def test_a_commands_event_and_log_line_are_made_in_the_history_process(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The daemon sends the command's plain facts; the other process makes the same event the
    daemon would have made, and the same log line, which comes back to the daemon's stderr."""
    caplog.set_level(logging.INFO)  # the process logs at the daemon's level
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection())
    log.start()
    try:
        _made_there(log, monkeypatch, capfd)
    finally:
        log.close()


def _made_there(
    log: HistoryProcess, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    expected = facts("t1")()  # made here, before making here is forbidden

    def not_here(self: CommandFacts) -> CommandEvent:
        raise AssertionError("a command's event was made in the daemon")

    monkeypatch.setattr(CommandFacts, "__call__", not_here)
    command = facts("t1")
    log.emit(WatchdogEvent(stalled_s=0.1), T0, 1)
    assert log.defer(Held([command, WatchdogEvent(stalled_s=0.2)], T0 + 1, 2, LogLine(command)))
    log.emit(WatchdogEvent(stalled_s=0.3), T0 + 2, 3)
    assert log.flush()
    assert stored(log) == [
        WatchdogEvent(stalled_s=0.1),
        expected,
        WatchdogEvent(stalled_s=0.2),
        WatchdogEvent(stalled_s=0.3),
    ]
    deadline = time.monotonic() + 5.0
    err = ""
    while "event=command tx=t1" not in err and time.monotonic() < deadline:
        time.sleep(0.02)  # the line is written by the process's log writer, then relayed
        err += capfd.readouterr().err
    [line] = [line for line in err.splitlines() if "event=command" in line]
    assert "level=info logger=machine event=command tx=t1 command=Home rider=r1" in line
    assert line.endswith("code=RESP_HOME_ACCEPTED state=HOMING")
    assert log.written == 4 and log.lost == 0


def test_past_its_bound_a_commands_log_line_still_follows_the_ones_queued_before_it(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A process that falls behind a command stream (run 51: 1,500 CheckHome beside two
    CPU-bound processes): the records past `DEFER_MAX` are made by the daemon, and their log
    lines used to be written at once, ahead of the lines still queued (1486..1500, then 1..)."""
    monkeypatch.setattr(eventlog, "DEFER_MAX", 2)
    caplog.set_level(logging.INFO)  # the process logs at the daemon's level
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection())
    log.start()
    stuck, go = threading.Event(), threading.Event()

    def hold_the_sender() -> None:  # a line that is not a command's: run as the batch is made
        stuck.set()
        go.wait(5.0)

    try:
        assert log.defer(Held([WatchdogEvent(stalled_s=0.0)], T0, 0, hold_the_sender))
        assert stuck.wait(5.0)
        commands = [facts(f"t{i}") for i in range(1, 6)]
        assert all(log.defer(Held([c], T0 + i, i, LogLine(c))) for i, c in enumerate(commands))
        assert command_tids(capfd.readouterr().err) == []  # none ahead of those queued
        go.set()
        assert log.flush()
        err, deadline = "", time.monotonic() + 5.0
        while err.count("event=command") < 5 and time.monotonic() < deadline:
            time.sleep(0.02)  # written by the process's log writer, then relayed
            err += capfd.readouterr().err
        assert command_tids(err) == ["t1", "t2", "t3", "t4", "t5"]
        assert [getattr(e, "transaction_id", None) for e in stored(log)[1:]] == [
            "t1",
            "t2",
            "t3",
            "t4",
            "t5",
        ]
    finally:
        go.set()
        log.close()


def test_listeners_get_the_rows_the_process_wrote(log: HistoryProcess) -> None:
    seen: list[StoredRow] = []
    log.subscribe(seen.extend)
    for i in range(5):
        log.emit(WatchdogEvent(stalled_s=float(i)), T0 + i, i)
    assert log.flush()
    assert [(row[0], row[4]) for row in seen] == [(i, "watchdog_trip") for i in range(1, 6)]


def test_a_killed_process_costs_only_what_it_had_not_written_and_a_new_one_takes_over(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Counted lost, recorded as `storage_failed` by the next process, which writes on."""
    monkeypatch.setattr(history_spawn, "RESPAWN_S", 0.05)
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection())
    log.start()
    try:
        _killed(log)
    finally:
        log.close()


def _kill_between_two(log: HistoryProcess) -> subprocess.Popen[bytes]:
    """One event written, the process SIGKILLed (and reaped), then a second event emitted."""
    log.emit(WatchdogEvent(stalled_s=1.0), T0, 1)
    assert log.flush()
    first = log._proc
    assert first is not None
    os.kill(first.pid, signal.SIGKILL)
    first.wait(5.0)
    log.emit(WatchdogEvent(stalled_s=2.0), T0 + 1, 2)
    return first


def _killed(log: HistoryProcess) -> None:
    first = _kill_between_two(log)
    assert log.flush(timeout=10.0)
    assert log._proc is not None and log._proc is not first
    kinds = [type(d).__name__ for d in stored(log)]
    assert kinds == ["WatchdogEvent", "StorageEvent", "WatchdogEvent"]
    failed = stored(log)[1]
    assert isinstance(failed, StorageEvent) and "exit code -9" in failed.error
    diag = log.diag()
    assert diag.failures == 1 and diag.lost == failed.lost == 0
    assert diag.written == 3


def test_an_event_sent_as_the_process_dies_waits_for_the_next_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The writer thread can send to a process that has died before the receiver saw it go:
    that batch reached no reader, so it goes to the next process instead of being lost."""
    monkeypatch.setattr(history_spawn, "RESPAWN_S", 0.05)
    noticed = threading.Event()
    ended = HistoryProcess._ended

    def held_back(self: HistoryProcess, proc: subprocess.Popen[bytes], code: int) -> None:
        assert noticed.wait(10.0)  # the receiver sees the death only once the batch was sent
        ended(self, proc, code)

    monkeypatch.setattr(HistoryProcess, "_ended", held_back)
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection())
    log.start()
    try:
        _kill_between_two(log)
        assert not log.flush(timeout=0.3)  # sent to the dead process: waiting, not lost
        assert log.lost == 0
        noticed.set()
        assert log.flush(timeout=10.0)
        stalls = [d.stalled_s for d in stored(log) if isinstance(d, WatchdogEvent)]
        assert stalls == [1.0, 2.0]
        assert log.diag().lost == 0
    finally:
        noticed.set()
        log.close()


@pytest.mark.hazard("H42")
def test_a_frozen_process_never_blocks_emit_and_close_ends_it_in_time(tmp_path: Path) -> None:
    # Another test's log that its failure left open may still have a process: only those
    # started here count (a failed test once left one, and this test failed on it too).
    others = set(history_processes())
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection(queue_capacity=64))
    log.start()
    proc = log._proc
    assert proc is not None
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        started = time.monotonic()
        for i in range(20_000):  # more than the pipe holds: the sender blocks, emit does not
            log.emit(WatchdogEvent(stalled_s=float(i)), T0, i)
        assert time.monotonic() - started < 10.0  # ~0.2 s; a blocked emit would never return
        assert log.dropped > 0
        assert not log.flush(timeout=0.2)
        closes_in_time(log, proc, others)
    finally:
        if proc.poll() is None:
            proc.kill()


def test_a_process_that_cannot_start_is_retried_with_a_growing_pause(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """E.g. a broken install: each attempt is counted and logged, and the attempts slow down."""
    broken = tmp_path / "python"
    broken.write_text("#!/bin/sh\nexit 3\n")
    broken.chmod(0o755)
    monkeypatch.setattr(history_spawn, "PYTHON", str(broken))
    monkeypatch.setattr(history_spawn, "RESPAWN_S", 0.05)
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection())
    log.start()
    try:
        deadline = time.monotonic() + 10.0
        while log.failures < 3 and time.monotonic() < deadline:
            log.emit(WatchdogEvent(stalled_s=0.0), T0, 0)
            time.sleep(0.05)
        assert log.failures >= 3
        assert "event writer process" in (log.last_error or "")
        ended = [r for r in caplog.records if "exit code 3" in r.getMessage()]
        assert ended and all(r.levelname == "ERROR" for r in ended)
        assert log._pause.seconds > history_spawn.RESPAWN_S
    finally:
        log.close()


class _GonePipe(_Pipe):
    """The pipe to a daemon that was killed: every write breaks (the real `send` around it)."""

    def __init__(self) -> None:
        self.tries = 0
        self._lock = threading.Lock()
        self._out = self  # type: ignore[assignment]

    def write(self, data: memoryview) -> int:
        self.tries += 1
        raise BrokenPipeError(32, "Broken pipe")


def test_rows_written_after_the_daemon_died_are_kept_not_counted_lost(tmp_path: Path) -> None:
    """A daemon killed before its history process wrote its last rows: they are stored, and
    the next start records no `storage_failed` for them (only the report back failed)."""
    pipe = _GonePipe()
    settings = WriterSettings.from_json(EventsSection().model_dump_json())
    writer = _Writer(pipe, tmp_path / EVENTS_FILE, "m1", settings)
    writer.start()
    try:
        writer.receive([("watchdog_trip", '{"kind":"watchdog_trip","stalled_s":0.1}', T0, 1)], 0)
        assert writer.flush()
    finally:
        writer.close()
    assert pipe.tries >= 1  # it did try to tell the daemon
    assert writer.lost == 0 and writer.failures == 0 and writer.last_error is None
    again = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection())
    again.start()
    try:
        again.emit_now(WatchdogEvent(stalled_s=0.2))
        assert again.flush()
        assert stored(again) == [WatchdogEvent(stalled_s=0.1), WatchdogEvent(stalled_s=0.2)]
    finally:
        again.close()


@pytest.mark.hazard("H41")
def test_a_process_whose_daemon_was_killed_before_it_started_writes_what_it_was_sent(
    tmp_path: Path,
) -> None:
    """A daemon SIGKILLed right after its start (a restart, then a kill, under load): its
    history process starts after it is gone, so its first word back finds no reader. It must
    still write the `daemon_start` it was sent, not die of the broken pipe."""
    proc = history_spawn.start_writer(
        tmp_path / EVENTS_FILE, "m1", EventsSection().model_dump_json()
    )
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdout.close()  # the daemon's end: gone before the process says a word
    start = '{"kind":"daemon_start","previous_stop_clean":true}'
    proc.stdin.write(encode([BATCH, 0, [(MADE, "daemon_start", start, T0, 0)], 0]))
    proc.stdin.close()
    assert proc.wait(timeout=FLUSH_S) == 0
    assert stored_kinds(tmp_path / EVENTS_FILE) == ["daemon_start"]


def test_an_event_sent_again_is_written_once(tmp_path: Path) -> None:
    """The safety events a process that ended had not confirmed are sent to the next one, which
    writes them unless they are stored already (killed after its write, before its word)."""
    settings = WriterSettings.from_json(EventsSection().model_dump_json())
    writer = _Writer(_GonePipe(), tmp_path / EVENTS_FILE, "m1", settings)
    writer.start()
    written = ("estop_pressed", '{"kind":"estop_pressed","state":"RUNNING"}', T0, 1)
    unwritten = ("watchdog_trip", '{"kind":"watchdog_trip","stalled_s":0.1}', T0 + 1, 2)
    try:
        writer.receive([written], 0)
        assert writer.flush()
        writer.receive([written, unwritten], 0, again=2)
        assert writer.flush()
    finally:
        writer.close()
    assert stored_kinds(tmp_path / EVENTS_FILE) == ["estop_pressed", "watchdog_trip"]
    assert writer.lost == 0


def test_a_stop_on_a_locked_database_leaves_the_e_stop_for_the_next_start(tmp_path: Path) -> None:
    """The daemon's stop (a flush, then `close` with its deadline) while another process locks
    the history: the process must end before the deadline, or it is killed before it keeps
    the E-stop it could not write. It was, about one stop in ten (a flush that waited longer
    than the daemon, a prune and a write each waiting a second on the lock)."""
    path = tmp_path / EVENTS_FILE
    log = HistoryProcess(path, "m1", EventsSection(prune_every_s=0.1))
    log.start()
    blocker = sqlite3.connect(path, timeout=0.1, isolation_level=None)
    try:
        log.emit(WatchdogEvent(stalled_s=0.0), T0, 0)
        assert log.flush()
        blocker.execute("BEGIN EXCLUSIVE")
        log.emit(EstopEvent(kind="estop_pressed", state=MachineState.RUNNING), T0 + 1, 1)
        deadline = time.monotonic() + 10.0
        while log.diag().failures == 0:  # the E-stop's write failed: it is held
            assert time.monotonic() < deadline, "the locked database was never tried"
            time.sleep(0.05)
        routine = CommandEvent(command="CheckHome", accepted=False, code="BUSY", message="-")
        log.emit(routine, T0 + 2, 2)  # in the daemon_stop's place: lost, and counted
        log.flush(timeout=1.0)  # the daemon's wind-down
        log.close()
        assert not log._cut_short, "killed at the deadline: what it held was lost"
    finally:
        blocker.close()
    again = EventLog(path, "m1", EventsSection())
    again.start()
    try:
        assert again.flush()
        events = read_page(connect(path), "m1", EventQuery(), 100).events
    finally:
        again.close()
    kinds = [e.kind for e in events]
    assert "estop_pressed" in kinds, kinds
    failed = [e.details for e in events if isinstance(e.details, StorageEvent)]
    assert failed and "in the previous run" in failed[0].error


def test_a_restart_reads_how_the_last_run_ended_once_its_writer_let_go(tmp_path: Path) -> None:
    """A run under load: a daemon killed soon after its start left its history process writing
    what it was sent, its `daemon_start` among it; the next daemon read the log before that and
    said the killed run had stopped cleanly. The restart waits for the previous writer."""
    path = tmp_path / EVENTS_FILE
    first = open_log(path)
    try:
        first.emit_now(DaemonStopEvent(reason="signal SIGTERM", exit_code=0))
        assert first.flush(timeout=FLUSH_S)
    finally:
        first.close()
    killed = open_log(path)  # the killed run's writer, still holding the log
    restart = HistoryProcess(path, "m1", EventsSection())
    starting = threading.Thread(target=restart.start, name="restart")
    try:
        starting.start()
        starting.join(0.5)
        assert starting.is_alive(), "the restart read the log before its writer let go"
        killed.emit_now(DaemonStartEvent(pid=2, hal="sim", period_s=0.01))
        assert killed.flush(timeout=FLUSH_S)
    finally:
        killed.close()
    starting.join(WRITER_WAIT_S + FLUSH_S)
    try:
        assert not starting.is_alive()
        assert restart.previous_stop_clean is False  # its last run wrote no daemon_stop
    finally:
        restart.close()
