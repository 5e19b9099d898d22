"""The event log when its storage fails: a database that cannot be written, is unusable, locked
by another process, on a full disk or a file system without locks; counted, reported, recovered
(moved from test_eventlog.py)."""

from __future__ import annotations

import contextlib
import errno
import os
import queue
import sqlite3
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from ride_machine.schema.events import (
    EventPage,
    EventQuery,
    StorageEvent,
)
from ride_machine.service.adapters import eventdb
from ride_machine.service.adapters.eventdb import BUSY_TIMEOUT_S
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.config.model import EventsSection
from tests.service.adapters.eventlog_support import T0, note, open_log, page


def test_a_database_that_cannot_be_written_is_reported_and_lost_events_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / EVENTS_FILE
    path.mkdir()  # a directory where the database belongs
    log = open_log(path)
    try:
        for i in range(20):
            log.emit_now(note(float(i)))
            assert log.flush()  # one batch each
        # One error line for the problem, not one per batch (all twenty counted in diag).
        errors = [r for r in caplog.records if "events_write_failed" in r.getMessage()]
        assert [r.levelname for r in errors if r.levelname == "ERROR"] == ["ERROR"]
        diag = log.diag()
        assert diag.failures >= 1 and diag.lost == 20
        assert diag.last_error is not None and "cannot open" in diag.last_error
    finally:
        log.close()


def test_a_recovered_database_records_the_failure_as_an_event(tmp_path: Path) -> None:
    log = open_log(tmp_path / EVENTS_FILE)
    try:
        blocker = sqlite3.connect(log.path, timeout=0.1)
        blocker.execute("BEGIN EXCLUSIVE")
        assert log.writer.conn is not None
        log.writer.conn.execute("PRAGMA busy_timeout=10")
        log.emit_now(note(1.0))
        assert log.flush()
        assert log.lost == 1
        blocker.rollback()
        blocker.close()
        log.emit_now(note(2.0))
        assert log.flush()
        first, second = page(log).events
        assert isinstance(first.details, StorageEvent) and first.details.lost == 1
        assert second.details == note(2.0)
    finally:
        log.close()


def _garbage(path: Path) -> None:
    path.write_bytes(b"not a database, just bytes " * 300)


def _foreign(path: Path) -> None:
    with contextlib.closing(sqlite3.connect(path)) as other:
        other.execute("CREATE TABLE events (id INTEGER PRIMARY KEY, what TEXT)")
        other.execute("INSERT INTO events VALUES (1, 'theirs')")
        other.commit()


@pytest.mark.hazard("H40")
@pytest.mark.parametrize("spoil", [_garbage, _foreign], ids=["garbage", "foreign-schema"])
def test_an_unusable_database_is_kept_aside_and_a_new_log_started(
    tmp_path: Path, spoil: Callable[[Path], None], kind: type[EventLog]
) -> None:
    path = tmp_path / EVENTS_FILE
    spoil(path)
    before = path.read_bytes()
    log = open_log(path, kind)
    try:
        log.emit_now(note(1.0))
        assert log.flush()
        [aside] = tmp_path.glob(f"{EVENTS_FILE}.bad-*")
        assert aside.read_bytes() == before  # kept as it was, for whoever wants to look
        first, second = page(log).events
        assert isinstance(first.details, StorageEvent)
        assert aside.name in first.details.error and "not a usable event log" in first.details.error
        assert second.details == note(1.0)
        assert log.diag().lost == 0
    finally:
        log.close()
    again = open_log(path, kind)  # the next start finds its own log: nothing more set aside
    again.close()
    assert len(list(tmp_path.glob(f"{EVENTS_FILE}.bad-*"))) == 1


def test_a_database_locked_by_another_process_never_holds_up_start_or_close(
    tmp_path: Path, kind: type[EventLog]
) -> None:
    path = tmp_path / EVENTS_FILE
    open_log(path).close()
    blocker = sqlite3.connect(path, timeout=0.1, isolation_level=None)
    blocker.execute("BEGIN EXCLUSIVE")
    try:
        started = time.monotonic()
        log = open_log(path, kind)
        log.emit_now(note(1.0))
        log.close()
        assert time.monotonic() - started < 2 * BUSY_TIMEOUT_S + 2.5
        assert log.diag().last_error is not None and "locked" in log.diag().last_error
        assert list(tmp_path.glob(f"{EVENTS_FILE}.bad-*")) == []  # locked is not broken
    finally:
        blocker.rollback()
        blocker.close()


def test_a_query_the_database_cannot_take_is_answered_and_the_reader_lives_on(
    any_log: EventLog,
) -> None:
    any_log.emit_now(note(1.0))
    assert any_log.flush()
    answers: queue.Queue[object] = queue.Queue()
    too_big = EventQuery(since=2**70)  # built directly, past the selector's checks
    assert any_log.read(too_big, answers.put, answers.put)
    assert "event log read failed" in str(answers.get(timeout=5.0))
    assert any_log.read(EventQuery(), answers.put, answers.put)
    answer = answers.get(timeout=5.0)
    assert isinstance(answer, EventPage) and len(answer.events) == 1


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 512 KiB tmpfs (we are root in the test environment; skipped where mount is refused)."""
    where = tmp_path / "disk"
    where.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=512k", "qa-small-disk", str(where)],
        capture_output=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def fill(disk: Path) -> Path:
    """Write a file on `disk` until it is full (ENOSPC); the file, to unlink for room again."""
    filler = disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    with contextlib.suppress(OSError):  # until ENOSPC
        while True:
            os.write(fd, b"x" * 4096)
    os.close(fd)
    return filler


@pytest.mark.hazard("H38")
def test_a_full_disk_costs_counted_events_keeps_the_history_readable_and_recovers(
    small_disk: Path, kind: type[EventLog]
) -> None:
    log = open_log(small_disk / EVENTS_FILE, kind)
    try:
        log.emit_now(note(1.0))
        assert log.flush()
        filler = fill(small_disk)
        # More than fits in what a prune frees: its checkpoint truncates the write-ahead log
        # (at a time of its own), which gives the small disk back a few pages; 50 events fit
        # there on a loaded host, and then nothing was lost.
        for i in range(1000):
            log.emit_now(note(2.0 + i))
        assert log.flush()
        assert log.lost > 0 and "full" in (log.diag().last_error or "")
        # The history is still readable while nothing can be written.
        answers: queue.Queue[object] = queue.Queue()
        assert log.read(EventQuery(), answers.put, answers.put)
        answer = answers.get(timeout=5.0)
        assert isinstance(answer, EventPage), answer
        assert answer.events[0].details == note(1.0)
        filler.unlink()
        log.emit_now(note(99.0))
        assert log.flush()
        kinds = [e.kind for e in page(log).events]
        assert kinds[-2:] == ["storage_failed", "session_ended"]
        failed = page(log).events[-2].details
        assert isinstance(failed, StorageEvent) and failed.lost == log.lost
    finally:
        log.close()


def test_a_log_started_on_a_full_disk_starts_and_writes_once_there_is_room(
    small_disk: Path, kind: type[EventLog]
) -> None:
    filler = fill(small_disk)  # before the log (or its lock) exists
    log = open_log(small_disk / EVENTS_FILE, kind)  # no exception: the machine runs on
    try:
        filler.unlink()
        log.emit_now(note(1.0))
        assert log.flush(timeout=10.0)
        assert [e.kind for e in page(log).events][-1] == "session_ended"
    finally:
        log.close()


def test_a_file_system_without_locks_is_written_unlocked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_locks(fd: int, operation: int) -> None:
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(eventdb.fcntl, "flock", no_locks)
    log = open_log(tmp_path / EVENTS_FILE)  # no exception: the machine runs on
    try:
        log.emit_now(note(1.0))
        assert log.flush()
        assert [e.kind for e in page(log).events] == ["session_ended"]
        assert log.last_error is None
    finally:
        log.close()


def test_a_writer_waits_for_the_one_before_it_to_let_go(
    tmp_path: Path, kind: type[EventLog]
) -> None:
    """The history process of a killed daemon may still be writing when the next daemon's
    writer starts: the new one waits for it, so the old run's last events come first."""
    path = tmp_path / EVENTS_FILE
    before = open_log(path)
    after = kind(path, "m1", EventsSection())
    starting = threading.Thread(target=after.start, daemon=True)
    starting.start()
    try:
        after.emit(note(2.0), T0 + 1, 2)
        assert not after.flush(timeout=0.3)  # it waits: nothing of it is written yet
        before.emit(note(1.0), T0, 1)
        before.close()  # writes its last event, then lets go
        starting.join(10.0)
        assert after.flush()
        assert [e.details.duration_s for e in page(after).events] == [1.0, 2.0]  # type: ignore[union-attr]
        assert after.last_error is None
    finally:
        before.close()
        after.close()


def test_a_writer_still_held_after_its_wait_writes_anyway_and_says_by_whom(tmp_path: Path) -> None:
    path = tmp_path / EVENTS_FILE
    fd, busy = eventdb.claim_writer(path, 0.0)  # another writer, here: this process
    assert fd is not None and busy is None
    try:
        log = EventLog(path, "m1", EventsSection(), writer_wait_s=0.05)
        log.start()
        try:
            log.emit(note(1.0), T0, 1)
            assert log.flush()  # nothing lost
            assert log.last_error is not None
            assert f"pid {os.getpid()}" in log.last_error
            assert "interleave" in log.last_error
        finally:
            log.close()
    finally:
        os.close(fd)
    again = open_log(path)  # let go: the next writer takes it at once, quietly
    assert again.last_error is None
    again.close()
