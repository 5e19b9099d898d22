"""A safety record nobody can flush (issue 43, point 8): kept by its own retention, apart from
routine events, and through a locked database and a stop (service/adapters/retention.py,
service/adapters/unwritten.py). The real daemon and a command flood: tests/integration/
test_safety_record.py."""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.schema.events import (
    CalibrationEvent,
    CommandEvent,
    EstopEvent,
    Event,
    EventQuery,
    FaultEvent,
    KnownDetails,
    ParamEvent,
    RiderEvent,
    StorageEvent,
)
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.eventdb import connect
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.eventread import read_page
from ride_machine.service.adapters.retention import SAFETY_KINDS, safety_bytes, used_bytes
from ride_machine.service.config.model import EventsSection

T0 = 1_800_000_000.0
MB = 1024 * 1024
PRUNE_WAIT_S = 10.0


def open_log(path: Path, **settings: object) -> EventLog:
    log = EventLog(path, "m1", EventsSection.model_validate(settings))
    log.start()
    return log


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / EVENTS_FILE


def routine(i: int, size: int = 1000) -> CommandEvent:
    """A refused `check/home`, as a command flood leaves them (with a long message)."""
    return CommandEvent(command="CheckHome", accepted=False, code="BUSY", message="x" * size)


def kinds(log: EventLog, *wanted: str) -> list[str]:
    with connect(log.path) as conn:
        page = read_page(conn, "m1", EventQuery(kinds=wanted), 500)
    return [e.kind for e in page.events]


def wait_pruned(log: EventLog, done: object) -> None:
    """Wake the writer until `done(conn)` holds (a prune is due every 0.1 s), bounded."""
    assert callable(done)
    wake = threading.Event()
    for _ in range(int(PRUNE_WAIT_S / 0.05)):
        with connect(log.path) as conn:
            if done(conn):
                return
        log.emit_now(routine(0, 10))
        wake.wait(0.05)
    raise AssertionError("retention did not prune in time")


SAFETY: list[KnownDetails] = [
    EstopEvent(kind="estop_pressed", state=MachineState.RUNNING),
    FaultEvent(kind="fault_raised", code="TILT_TIMEOUT", message="tilt stuck"),
    RiderEvent(kind="rider_lost", rider="bay1/ab12", policy="pause", acted=True),
    # Who entered which gain (issue 58, point 5: a flood of commands flushed these).
    CalibrationEvent(axis="tilt", new={"gain_counts_per_deg": 52.0}, persisted=True),
    ParamEvent(name="tilt.max_deg", old=60.0, new=50.0, persisted=True, by="bay1/ab12"),
]


def test_a_flood_of_routine_events_prunes_routine_events_only(path: Path) -> None:
    """The reproduction in small: a 1 MB history, an E-stop, a fault and a lost Rider, then
    3 MB of refused commands: the history keeps to 1 MB and all three are still there."""
    log = open_log(path, max_mb=1, prune_every_s=0.1, queue_capacity=100_000)
    try:
        for details in SAFETY:
            log.emit(details, T0, 1)
        for i in range(3000):
            log.emit(routine(i), T0 + 1 + i / 1000, None)
            if i % 500 == 0:
                assert log.flush()
        assert log.flush()
        wait_pruned(log, lambda conn: used_bytes(conn) <= MB)
        assert kinds(log, *SAFETY_KINDS) == [
            "estop_pressed",
            "fault_raised",
            "rider_lost",
            "calibration",
            "param_changed",
        ]
        with connect(path) as conn:
            [(first,)] = conn.execute("SELECT MIN(seq) FROM events WHERE kind = 'command'")
        assert first > 100  # the oldest routine events went
    finally:
        log.close()


@pytest.mark.hazard("H41")
def test_the_safety_record_keeps_to_its_own_limit_causable_events_first(path: Path) -> None:
    """Faults a `rider` login can cause at will (an invalid session) fill the safety record:
    the oldest of them go, never the E-stop before them."""
    log = open_log(path, safety_max_mb=0.1, prune_every_s=0.1, queue_capacity=100_000)
    try:
        log.emit(SAFETY[0], T0, 1)
        for i in range(300):  # about 0.3 MB of faults
            log.emit(
                FaultEvent(kind="fault_raised", code="INVALID_SESSION", message="y" * 1000),
                T0 + 1 + i,
                None,
            )
        assert log.flush()
        wait_pruned(log, lambda conn: safety_bytes(conn) <= 0.1 * MB)
        left = kinds(log, *SAFETY_KINDS)
        assert left[0] == "estop_pressed" and 0 < left.count("fault_raised") < 300
    finally:
        log.close()


@pytest.fixture
def blocker(path: Path) -> Iterator[sqlite3.Connection]:
    """Another process's lock on the history (a backup, a reader holding a write lock)."""
    conn = sqlite3.connect(path, timeout=0.1, isolation_level=None)
    yield conn
    conn.close()


def locked_out(path: Path, blocker: sqlite3.Connection) -> EventLog:
    """A log whose database `blocker` locks: an E-stop and a routine event it cannot write."""
    log = open_log(path)
    assert log.writer.conn is not None
    log.writer.conn.execute("PRAGMA busy_timeout=10")  # a failed write in 10 ms, not 1 s
    blocker.execute("BEGIN EXCLUSIVE")
    log.emit(SAFETY[0], T0, 1)
    log.emit(routine(1, 10), T0 + 1, 2)
    assert log.flush()
    return log


def written_after(log: EventLog) -> list[Event]:
    """One more routine event written, then everything the database holds."""
    log.emit(routine(2, 10), T0 + 2, 3)
    assert log.flush()
    with connect(log.path) as conn:
        return read_page(conn, "m1", EventQuery(), 100).events


def test_the_safety_record_waits_for_a_locked_database(
    path: Path, blocker: sqlite3.Connection
) -> None:
    log = locked_out(path, blocker)
    try:
        assert log.lost == 1  # the routine one; the E-stop waits in memory
        blocker.execute("ROLLBACK")
        events = written_after(log)
        stored = [e.kind for e in events]
        assert stored[-3:] == ["storage_failed", "estop_pressed", "command"], stored
        assert isinstance(events[-3].details, StorageEvent) and events[-3].details.lost == 1
    finally:
        log.close()


def test_what_a_locked_database_kept_out_is_written_after_a_restart(
    path: Path, blocker: sqlite3.Connection
) -> None:
    """Still locked at the stop: the held E-stop and the count of the lost events go into the
    file reserved at the start, and the next start writes both."""
    locked_out(path, blocker).close()
    blocker.execute("ROLLBACK")
    again = open_log(path)
    try:
        events = written_after(again)
    finally:
        again.close()
    by_kind = {e.kind: e for e in events}
    assert by_kind["estop_pressed"].time == T0
    failed = by_kind["storage_failed"].details
    assert isinstance(failed, StorageEvent) and failed.lost >= 1
    assert "in the previous run" in failed.error
