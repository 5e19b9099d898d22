"""A safety record nobody can flush (issue 43, reproduction 8), with a real daemon.

About 260 000 `check/home` commands pushed the history past its 64 MB, and the next prune took an
E-stop from two minutes before; a locked database lost E-stop events for good. Here the history
is 1 MB (the same prune, a thousandth of the commands): the flood prunes routine events only.
And an E-stop pressed while another process holds the database is written once it lets go,
or, still locked at the stop, by the next start.
"""

from __future__ import annotations

import contextlib
import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from ride_machine.rider.client import Rider
from ride_machine.schema.calibration import TiltCalibrationSet
from ride_machine.schema.codec import Format, encode
from ride_machine.schema.commands import CommandRequest
from ride_machine.schema.events import EventQuery
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.eventlog import EVENTS_FILE
from tests.integration.support import write_fast_config
from tests.procs import Daemon, start_daemon

pytestmark = pytest.mark.integration

HISTORY = """
[events]
max_mb = 1
prune_every_s = 0.2
"""
FLOOD = 6000
"""`check/home` commands: about 1.5 MB of `command` events, half again the history's limit."""
WINDOW = 32
"""Commands in flight at once (below the bus's 64 waiting for the scan loop)."""
WAIT_S = 30.0


def machine(tmp: Path) -> Daemon:
    config = write_fast_config(tmp)
    config.write_text(config.read_text() + HISTORY)
    return start_daemon(tmp, extra=["--config", str(config)])


def estop(r: Rider) -> None:
    """Press and release the E-stop (the simulator's input), seen by the scan loop."""
    r.sim("estop", pressed=True)
    r.wait_for({MachineState.FAULT_ESTOP}, WAIT_S)
    r.sim("estop", pressed=False)


def flood(r: Rider, count: int) -> None:
    """`count` check/home commands, `WINDOW` in flight, each answered (bounded)."""
    window = threading.Semaphore(WINDOW)
    answered = threading.Semaphore(0)
    key = f"{r.base}/cmd/check/home"
    for i in range(count):
        assert window.acquire(timeout=WAIT_S), "the machine stopped answering the flood"

        def done(window: threading.Semaphore = window) -> None:
            window.release()
            answered.release()

        payload = encode(CommandRequest(transaction_id=f"flood-{i}"))
        r.session.get(
            key,
            zenoh.handlers.Callback(lambda _: None, done),
            payload=payload,
            encoding=Format.MSGPACK.value,
            timeout=WAIT_S,
        )
    for _ in range(count):
        assert answered.acquire(timeout=WAIT_S)


def oldest_command(data_dir: Path) -> int:
    with contextlib.closing(
        sqlite3.connect(f"file:{data_dir / EVENTS_FILE}?mode=ro", uri=True)
    ) as c:
        [(seq,)] = c.execute("SELECT COALESCE(MIN(seq), 0) FROM events WHERE kind = 'command'")
    return int(seq)


def estops(r: Rider) -> list[str]:
    return [e.kind for e in r.events(EventQuery(kinds=("estop_pressed", "estop_released")))]


def kept_changes(r: Rider) -> list[str]:
    """The calibration and parameter rows, oldest first (issue 58, point 5)."""
    return [e.kind for e in r.events(EventQuery(kinds=("calibration", "param_changed")))]


@pytest.mark.hazard("H41")
def test_a_command_flood_prunes_commands_never_the_e_stop(tmp_path: Path) -> None:
    """Nor a calibration or a parameter entered before it (issue 58, point 5: who entered which
    gain two minutes before went with a flood of cheap commands)."""
    daemon = machine(tmp_path)
    try:
        with daemon.rider(supervise=False) as r:
            estop(r)
            assert r.events(EventQuery(kinds=("command",), last=1)) == []  # none before it
            r.set_calibration(tilt=TiltCalibrationSet(offset_counts=1210, gain_counts_per_deg=40))
            r.set_param("bus.heartbeat_s", 2.0)
            deadline = time.monotonic() + WAIT_S
            while sorted(changes := kept_changes(r)) != ["calibration", "param_changed"]:
                assert time.monotonic() < deadline, changes  # written by the history process
                time.sleep(0.05)
            flood(r, FLOOD)
            deadline = time.monotonic() + WAIT_S
            while oldest_command(daemon.data_dir) < FLOOD // 10:  # the prune took the oldest
                assert time.monotonic() < deadline, "the history was never pruned"
                time.sleep(0.2)
            kept = estops(r)
            kept_after = kept_changes(r)
    finally:
        daemon.stop()
    assert kept == ["estop_pressed", "estop_released"]
    assert kept_after == changes


@contextlib.contextmanager
def locked(data_dir: Path) -> Iterator[None]:
    """Another process's exclusive lock on the history, as a backup tool may take it."""
    with contextlib.closing(sqlite3.connect(data_dir / EVENTS_FILE, isolation_level=None)) as c:
        c.execute("BEGIN EXCLUSIVE")
        try:
            yield
        finally:
            c.execute("ROLLBACK")


def wait_failures(r: Rider) -> None:
    """Until the history has failed to write while locked (its diagnostics say so)."""
    deadline = time.monotonic() + WAIT_S
    while (events := r.diag().events) is None or events.failures == 0:
        assert time.monotonic() < deadline, "the history never tried the locked database"
        time.sleep(0.1)


@pytest.mark.hazard("H41")
def test_an_e_stop_pressed_while_the_history_is_locked_is_written_when_it_opens(
    tmp_path: Path,
) -> None:
    daemon = machine(tmp_path)
    try:
        with daemon.rider(supervise=False) as r:
            with locked(daemon.data_dir):
                estop(r)
                wait_failures(r)
            deadline = time.monotonic() + WAIT_S
            while (kept := estops(r)) != ["estop_pressed", "estop_released"]:
                assert time.monotonic() < deadline, kept
                time.sleep(0.1)
    finally:
        daemon.stop()


@pytest.mark.hazard("H41")
def test_an_e_stop_still_unwritten_at_the_stop_is_written_by_the_next_start(
    tmp_path: Path,
) -> None:
    daemon = machine(tmp_path)
    with locked(daemon.data_dir):
        try:
            with daemon.rider(supervise=False) as r:
                estop(r)
                wait_failures(r)
        finally:
            daemon.stop()
    daemon = machine(tmp_path)
    try:
        with daemon.rider(supervise=False) as r:
            kept = estops(r)
            failed = [
                e.details
                for e in r.events(EventQuery(kinds=("storage_failed",)))
                if "in the previous run" in str(e.details)
            ]
    finally:
        daemon.stop()
    assert kept == ["estop_pressed", "estop_released"]
    assert failed, "the next start did not say what the last run could not write"
