"""The daemon's assembly: setup steps undone in reverse order, outputs safe first, any way out."""

from __future__ import annotations

import contextlib
import logging
import socket
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.schema.events import DaemonStopEvent, EventQuery
from ride_machine.service.adapters.eventdb import connect_readonly
from ride_machine.service.adapters.eventlog import EVENTS_FILE
from ride_machine.service.adapters.eventread import iter_events
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.loop import ScanLoop
from ride_machine.service.core.scan.tuning import set_timer_slack, timer_slack
from ride_machine.service.supervision.assembly import DaemonOptions
from ride_machine.service.supervision.daemon import Daemon
from ride_machine.service.supervision.outcome import EXIT_FAILED, EXIT_OK
from tests.procs import free_port, write_zenoh_config

# Setup order reversed: the outputs first, the HAL last.
UNDO_ORDER = [
    "outputs_safe",
    "fastdata",
    "watchdog",
    "wind_down",
    "bus",
    "session",
    "event_log",
    "calibration",
    "storage",
    "hal",
]


@pytest.fixture(autouse=True)
def keep_process_state() -> Iterator[None]:
    """The daemon runs on this (pytest's main) thread: it tunes the thread's timer slack and
    the process's GIL switch interval. Give pytest its own back, or later tests inherit the
    daemon's (its SIGTERM/SIGINT handlers tests/conftest.py gives back after every test)."""
    slack = timer_slack()
    interval = sys.getswitchinterval()
    yield
    if slack is not None:
        set_timer_slack(slack)
    sys.setswitchinterval(interval)


def daemon_in(tmp_path: Path, fastdata_port: int) -> Daemon:
    config = MachineConfig().with_overrides(
        loop={"gc_freeze": False},  # not in the test process
        fastdata={"enabled": True, "host": "127.0.0.1", "port": fastdata_port},
    )
    config = config.model_copy(update={"data_dir": str(tmp_path / "data")})
    options = DaemonOptions(
        zenoh_config=write_zenoh_config(tmp_path), listen=[f"tcp/127.0.0.1:{free_port()}"]
    )
    return Daemon(config, options)


def undone(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [
        r.getMessage().removeprefix("event=undo step=")
        for r in caplog.records
        if r.getMessage().startswith("event=undo ")
    ]


def stop_after_cycles(daemon: Daemon, cycles: int) -> threading.Thread:
    def watch() -> None:
        for _ in range(1000):  # bounded: 10 s
            runner = daemon.runner
            if runner is not None and runner.pulse.count >= cycles:
                runner.stop()
                return
            threading.Event().wait(0.01)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def stops_recorded(data_dir: Path) -> list[tuple[str, int]]:
    """(reason, exit code) of each `daemon_stop` in the event history."""
    with contextlib.closing(connect_readonly(data_dir / EVENTS_FILE)) as conn:
        events = iter_events(conn, EventQuery(kinds=("daemon_stop",)))
        return [
            (e.details.reason, e.details.exit_code)
            for e in events
            if isinstance(e.details, DaemonStopEvent)
        ]


def test_teardown_runs_setup_in_reverse_with_outputs_safe_first(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="machine")
    daemon = daemon_in(tmp_path, free_udp_port())
    watcher = stop_after_cycles(daemon, 5)
    assert daemon.run() == EXIT_OK
    watcher.join(timeout=10)
    assert undone(caplog) == UNDO_ORDER
    assert not daemon.raw_hal.outputs.any_on()
    stopped = [r.getMessage() for r in caplog.records if "event=stopped" in r.getMessage()]
    assert len(stopped) == 1 and stopped[0].startswith("event=stopped code=0 outputs=safe")
    assert stops_recorded(tmp_path / "data") == [("runner stopped", EXIT_OK)]


def test_a_failing_setup_step_undoes_the_steps_before_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="machine")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        daemon = daemon_in(tmp_path, taken.getsockname()[1])
        with pytest.raises(OSError):
            daemon.run()  # the FastData port is in use: the last step before serving fails
    assert undone(caplog) == UNDO_ORDER[1:]  # nothing had driven an output yet
    assert not daemon.raw_hal.outputs.any_on()
    assert not any("event=stopped" in r.getMessage() for r in caplog.records)
    # Recorded by the event log's own undo, the bus having gone by then.
    [(reason, code)] = stops_recorded(tmp_path / "data")
    assert reason.startswith("start failed: ") and code == EXIT_FAILED


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def test_a_slow_teardown_is_not_a_watchdog_trip(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The loop stopped on purpose beats no more: a teardown step that takes longer than the
    watchdog's limit (a loaded host; here `go_safe` held up 10 limits) must not be reported
    as a stalled loop (a FAULT_HW status and a `watchdog_trip` in the history at every such
    stop, seen under `machine supervise` on a loaded host)."""
    caplog.set_level(logging.DEBUG, logger="machine")
    go_safe = ScanLoop.go_safe
    limit = MachineConfig().loop.period_s * MachineConfig().loop.watchdog_periods
    held_s = 10 * limit
    stalled = threading.Event()

    def slow_go_safe(loop: ScanLoop) -> None:
        go_safe(loop)
        if daemon.runner is not None and daemon.runner.stop_event.is_set():
            stalled.wait(held_s)  # never set: a teardown step held up

    monkeypatch.setattr(ScanLoop, "go_safe", slow_go_safe)
    daemon = daemon_in(tmp_path, free_udp_port())
    watcher = stop_after_cycles(daemon, 20)
    assert daemon.run() == EXIT_OK
    watcher.join(timeout=10)
    assert not any("event=watchdog_trip" in r.getMessage() for r in caplog.records)
    with contextlib.closing(connect_readonly(tmp_path / "data" / EVENTS_FILE)) as conn:
        assert list(iter_events(conn, EventQuery(kinds=("watchdog_trip",)))) == []
