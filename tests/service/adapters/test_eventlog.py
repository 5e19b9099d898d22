"""The event log on disk: what is written reads back, pages, drops are counted, retention holds.

The tests that take `kind` run on both writers: a thread of the daemon (`EventLog`) and a
process of its own (`HistoryProcess`, `[events] process = true`, the default)."""

from __future__ import annotations

import logging
import sqlite3
import threading
from pathlib import Path

import pytest

from ride_machine.schema.codec import dump_json, encode
from ride_machine.schema.events import (
    CommandEvent,
    DaemonStartEvent,
    DaemonStopEvent,
    EventQuery,
    KnownDetails,
    QueryError,
    StorageEvent,
)
from ride_machine.service.adapters import eventdb, eventlog
from ride_machine.service.adapters.eventdb import StoredRow, connect
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.eventread import iter_events, row_event, row_payload
from ride_machine.service.adapters.retention import used_bytes
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.held import Held, LogLine
from tests.schema.event_samples import DETAILS
from tests.service.adapters.eventlog_support import (
    FLUSH_S,
    T0,
    command_tids,
    facts,
    note,
    open_log,
    page,
)


def test_written_events_read_back_in_order_with_seq_time_and_cycle(any_log: EventLog) -> None:
    for i in range(5):
        any_log.emit(note(i / 10), T0 + i, 10 + i)
    assert any_log.flush()
    got = page(any_log)
    assert [e.seq for e in got.events] == [1, 2, 3, 4, 5]
    assert [e.time for e in got.events] == [T0 + i for i in range(5)]
    assert [e.cycle for e in got.events] == [10, 11, 12, 13, 14]
    assert got.events[2].details == note(0.2)
    assert (got.more, got.first_seq, got.last_seq) == (False, 1, 5)


def test_listeners_get_each_committed_batch_with_its_seq(any_log: EventLog) -> None:
    seen: list[StoredRow] = []
    any_log.subscribe(seen.extend)
    any_log.emit_now(DaemonStopEvent(reason="test", exit_code=0))
    any_log.emit(note(0.5), T0, 7)
    assert any_log.flush()
    events = [row_event(row) for row in seen]
    assert [(e.seq, e.kind, e.cycle) for e in events] == [
        (1, "daemon_stop", None),
        (2, "session_ended", 7),
    ]
    assert events == page(any_log).events  # what listeners get is what is stored


def test_listeners_get_the_stored_seq_of_every_row_after_a_prune_and_a_reopen(
    tmp_path: Path, kind: type[EventLog]
) -> None:
    """A batch is inserted in one statement and numbered from SQLite's last row id: the seq
    a listener gets is the stored one, also once the oldest rows are gone (AUTOINCREMENT never
    reuses a number) and in a log opened again."""
    path = tmp_path / EVENTS_FILE
    first = open_log(path, kind)
    for i in range(4):
        first.emit(note(float(i)), T0 + i, i)
    assert first.flush()
    first.close()
    with connect(path) as conn:
        conn.execute("DELETE FROM events WHERE seq >= 3")  # the newest gone: a max() would reuse 3
    log = open_log(path, kind, batch_max=3)
    try:
        seen: list[StoredRow] = []
        log.subscribe(seen.extend)
        for i in range(7):
            log.emit(note(float(i)), T0 + i, 100 + i)
        assert log.flush()
        assert [row[0] for row in seen] == list(range(5, 12))
        assert [row_event(row) for row in seen] == page(log, since=5).events
    finally:
        log.close()


@pytest.mark.parametrize("details", DETAILS, ids=lambda d: type(d).__name__)
def test_a_rows_wire_bytes_are_its_events_encoding(details: KnownDetails) -> None:
    """The bus publishes `row_payload(row)`, made without the model: the same bytes as the
    `Event`'s own encoding, for every kind, including times and cycles of every shape."""
    for seq, when, cycle in [(1, T0, None), (2**40, 1.0000000000000002, 2**31), (3, 0.0, 0)]:
        row = (seq, when, cycle, "machine-7", details.kind, dump_json(details))
        assert row_payload(row) == encode(row_event(row))
        assert row_event(row).details == details


def test_pages_are_bounded_and_continue_from_next_since(tmp_path: Path) -> None:
    log = open_log(tmp_path / EVENTS_FILE, page_max=4)
    try:
        for i in range(10):
            log.emit(note(float(i)), T0 + i, None)
        assert log.flush()
        seqs, since = [], None
        while True:
            got = page(log, since=since)
            assert len(got.events) <= 4
            seqs += [e.seq for e in got.events]
            if not got.more:
                break
            since = got.next_since
        assert seqs == list(range(1, 11))
        assert [e.seq for e in page(log, last=3).events] == [8, 9, 10]
        assert [e.seq for e in page(log, since=2, until=3).events] == [2, 3]
        assert [e.seq for e in page(log, since_time=T0 + 5, until_time=T0 + 6).events] == [6, 7]
    finally:
        log.close()


def test_kind_filter(any_log: EventLog) -> None:
    any_log.emit_now(note(1.0))
    any_log.emit_now(DaemonStopEvent(reason="x", exit_code=1))
    any_log.emit_now(note(2.0))
    assert any_log.flush()
    assert [e.seq for e in page(any_log, kinds=("session_ended",)).events] == [1, 3]
    with connect(any_log.path) as conn:
        assert len(list(iter_events(conn, EventQuery(kinds=("daemon_stop",)), chunk=1))) == 1


def test_a_held_record_is_made_on_the_writer_in_its_place_among_the_events(
    any_log: EventLog,
) -> None:
    """A command's held record (`defer`) becomes its events, with its own time and cycle,
    between the events queued before and after it, and its log line is written by the writer."""
    threads: list[str] = []
    made: list[str] = []

    def command_event() -> KnownDetails:
        made.append(threading.current_thread().name)
        return DETAILS[0]

    any_log.emit(note(0.1), T0, 1)
    held = Held([command_event, DETAILS[1]], T0 + 1, 2, lambda: threads.append("then"))
    assert any_log.defer(held)
    any_log.emit(note(0.3), T0 + 2, 3)
    assert any_log.flush()
    events = page(any_log).events
    assert [e.details for e in events] == [
        note(0.1),
        DETAILS[0],
        DETAILS[1],
        note(0.3),
    ]
    assert [(e.time, e.cycle) for e in events[1:3]] == [(T0 + 1, 2), (T0 + 1, 2)]
    assert made == ["eventlog"] and threads == ["then"]
    assert any_log.queued == 0


def test_defer_is_refused_before_start_and_after_close_and_past_its_bound_made_in_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Refused, the caller makes the record itself (`held.write(log.emit)`). Past its bound the
    log makes the record's events on the caller's thread and queues its log line in its place:
    nothing is lost and the order of events and lines stays (run 51: the lines of the records
    past the bound were written ahead of those still queued)."""
    caplog.set_level(logging.INFO, logger="machine")
    monkeypatch.setattr(eventlog, "DEFER_MAX", 2)
    log = EventLog(tmp_path / EVENTS_FILE, "m1", EventsSection())
    assert not log.defer(Held([], T0, 0, None))  # no writer yet
    log.start()
    stuck, go = threading.Event(), threading.Event()

    def hold_the_writer() -> None:
        stuck.set()
        go.wait(5.0)

    try:
        assert log.defer(Held([note(0.0)], T0, 0, hold_the_writer))
        assert stuck.wait(5.0)  # the writer is making it: the next ones wait in the queue
        commands = [facts(f"t{i}") for i in (1, 2, 3, 4)]
        records = [
            Held([note(float(i)), c], T0 + i, i, LogLine(c)) for i, c in enumerate(commands, 1)
        ]
        assert [log.defer(h) for h in records] == [True] * 4
        assert command_tids(caplog.text) == []  # none written ahead of those queued
        go.set()
        assert log.flush()
        made = [e.details for e in page(log).events]
        assert [d.transaction_id if d.kind == "command" else d.duration_s for d in made] == [  # type: ignore[union-attr]
            0.0,
            1.0,
            "t1",
            2.0,
            "t2",
            3.0,
            "t3",
            4.0,
            "t4",
        ]
        assert command_tids(caplog.text) == ["t1", "t2", "t3", "t4"]
    finally:
        go.set()
        log.close()
    assert not log.defer(Held([], T0, 0, None))  # stopped


def test_a_held_record_that_cannot_be_made_is_counted_lost_and_the_writer_goes_on(
    any_log: EventLog,
) -> None:
    def broken() -> KnownDetails:
        raise RuntimeError("bug")

    assert any_log.defer(Held([broken], T0, 1, None))
    any_log.emit(note(0.5), T0 + 1, 2)
    assert any_log.flush()
    assert [e.details for e in page(any_log).events] == [note(0.5)]
    assert any_log.lost == 1


def test_a_batch_that_fails_unexpectedly_is_counted_lost_and_the_writer_goes_on(
    log: EventLog, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A bug, not a disk: the batch is lost and counted, the history goes on and says so."""
    write = EventLog._write
    batches: list[int] = []

    def failing_once(self: EventLog, batch: list[eventdb.Row]) -> None:
        batches.append(len(batch))
        if len(batches) == 1:
            raise RuntimeError("bug in a batch")
        write(self, batch)

    monkeypatch.setattr(EventLog, "_write", failing_once)
    log.emit(note(0.1), T0, 1)
    assert log.flush()
    log.emit(note(0.2), T0 + 1, 2)
    assert log.flush()
    error = "event writer failed: RuntimeError('bug in a batch')"
    assert [e.details for e in page(log).events] == [
        StorageEvent(what="events", error=error, lost=1),
        note(0.2),
    ]
    assert (log.lost, log.failures, log.last_error) == (1, 1, error)
    assert log._thread is not None and log._thread.is_alive()
    [record] = [r for r in caplog.records if "events_write_failed" in r.getMessage()]
    assert record.exc_info is not None  # a bug: its traceback is in the log


def test_a_prune_that_fails_unexpectedly_leaves_the_writer_running(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(self: EventLog) -> None:
        self.writer.prune_due = self.wall() + self.settings.prune_every_s
        raise RuntimeError("bug in a prune")

    monkeypatch.setattr(EventLog, "_prune", broken)
    now = [T0]
    log = EventLog(tmp_path / EVENTS_FILE, "m1", EventsSection(), wall=lambda: now[0])
    log.start()
    try:
        for i in range(3):
            now[0] += log.settings.prune_every_s  # a prune is due after each write
            log.emit(note(i / 10), T0 + i, i)
            assert log.flush()
        assert log.failures >= 2  # the third prune may still be under way
        assert log.lost == 0
        details = [e.details for e in page(log).events]
        assert details[-1] == note(0.2)
        assert (
            StorageEvent(what="events", error="event prune failed: RuntimeError('bug in a prune')")
            in details
        )
        assert log._thread is not None and log._thread.is_alive()
    finally:
        log.close()


@pytest.mark.hazard("H42")
def test_emit_never_blocks_while_the_writer_holds_the_database(
    tmp_path: Path, kind: type[EventLog]
) -> None:
    log = open_log(tmp_path / EVENTS_FILE, kind, queue_capacity=16)
    blocker = sqlite3.connect(log.path, timeout=0.1)
    try:
        blocker.execute("BEGIN IMMEDIATE")  # the writer's next commit waits on this lock
        for i in range(100):
            log.emit(note(float(i)), T0 + i, i)  # returns at once
        assert log.dropped >= 100 - 16 - log.settings.batch_max
    finally:
        blocker.rollback()
        blocker.close()
    assert log.flush()
    log.close()


def test_retention_prunes_by_age_and_seq_keeps_growing(tmp_path: Path) -> None:
    now = [1_000_000.0]
    log = EventLog(
        tmp_path / EVENTS_FILE,
        "m1",
        EventsSection(max_age_days=1, prune_every_s=0.1),
        wall=lambda: now[0],
    )
    log.start()
    try:
        for day in (0, 1, 2):
            log.emit(note(float(day)), now[0] - (2 - day) * 86_400 - 1, None)
        assert log.flush()
        now[0] += 1.0  # prune is due
        log.emit_now(note(9.0))
        assert log.flush()
        deadline = threading.Event()
        for _ in range(100):
            if page(log).first_seq == 3:
                break
            deadline.wait(0.02)
        got = page(log)
        assert [e.seq for e in got.events] == [3, 4]
    finally:
        log.close()


def test_retention_keeps_the_database_under_max_mb(tmp_path: Path, kind: type[EventLog]) -> None:
    log = open_log(
        tmp_path / EVENTS_FILE, kind, max_mb=1, prune_every_s=0.1, queue_capacity=100_000
    )
    try:
        big = "x" * 1000
        for i in range(3000):  # about 3 MB of events
            refused = CommandEvent(command="CheckHome", accepted=False, code="BUSY", message=big)
            log.emit(refused, T0 + i / 1000, None)  # routine: retention's max_mb applies
            if i % 500 == 0:
                assert log.flush()
        assert log.flush()
        for _ in range(100):
            with connect(log.path) as conn:
                if used_bytes(conn) <= 1024 * 1024:
                    break
            threading.Event().wait(0.05)
            log.emit_now(note(0.0))  # wakes the writer, prune is due
        with connect(log.path) as conn:
            assert used_bytes(conn) <= 1024 * 1024
            [(kept,)] = conn.execute("SELECT COUNT(*) FROM events").fetchall()
        # Pruned down to the limit, not emptied: a prune leaves 90 % of the limit (~480 of these
        # rows), and the rows written after the last prune add to that.
        assert kept > 400
        got = page(log, last=1)
        assert got.first_seq is not None and got.first_seq > 1  # the oldest are gone
        assert got.events[-1].seq >= 3000  # the newest are kept, seq never reused
        assert log.dropped == 0
    finally:
        log.close()


@pytest.mark.hazard("H43")
def test_a_restart_knows_whether_the_last_run_stopped_cleanly(
    tmp_path: Path, kind: type[EventLog]
) -> None:
    """Each run's events are flushed before it closes: `close` is bounded (2 s) and a history
    process that a loaded host had not yet started writing in that time was killed with the
    start event unwritten (a run under load)."""
    path = tmp_path / EVENTS_FILE
    log = open_log(path, kind)
    try:
        assert log.previous_stop_clean is None
        log.emit_now(DaemonStartEvent(pid=1, hal="sim", period_s=0.01))
        assert log.flush(timeout=FLUSH_S)
    finally:
        log.close()
    log = open_log(path, kind)
    try:
        assert log.previous_stop_clean is False  # the last run never wrote daemon_stop
        log.emit_now(DaemonStopEvent(reason="signal SIGTERM", exit_code=0))
        assert log.flush(timeout=FLUSH_S)
    finally:
        log.close()
    log = open_log(path, kind)
    try:
        assert log.previous_stop_clean is True
    finally:
        log.close()


@pytest.mark.parametrize(
    ("text", "param"),
    [
        ("since=abc", "since"),
        ("limit=0", "limit"),
        ("kind=bogus", "kind"),
        ("color=red", "color"),
        ("since_time=yesterday", "since_time"),
        ("since=99999999999999999999999", "since"),  # past SQLite's INTEGER
        ("until=-3", "until"),
        ("since_time=nan", "since_time"),
    ],
)
def test_bad_query_parameters_name_the_parameter(text: str, param: str) -> None:
    with pytest.raises(QueryError) as err:
        EventQuery.from_text(text)
    assert err.value.param == param


def test_query_text_round_trips_with_either_separator() -> None:
    q = EventQuery(since=3, until=9, kinds=("command", "state"), limit=5)
    assert EventQuery.from_text(q.params()) == q
    assert EventQuery.from_text(q.params().replace(";", "&")) == q
