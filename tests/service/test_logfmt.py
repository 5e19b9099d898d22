"""Structured log lines: the timestamp stays right although it is formatted once per second."""

from __future__ import annotations

import io
import logging
import re
import threading
import time

import pytest

from ride_machine.service import logfmt
from ride_machine.service.logfmt import KeyValueFormatter, LineHandler, LineQueue, LineWriter


def _record(created: float) -> logging.LogRecord:
    record = logging.LogRecord("machine", logging.INFO, __file__, 1, "event=x a=%s", ("1",), None)
    record.created = created
    record.msecs = (created - int(created)) * 1000
    return record


def test_each_line_has_its_own_second_and_millisecond() -> None:
    fmt = KeyValueFormatter()
    lines = [fmt.format(_record(t)) for t in (1764300000.125, 1764300000.990, 1764300001.002)]
    assert lines == [
        "ts=2025-11-28T03:20:00.125Z level=info logger=machine event=x a=1",
        "ts=2025-11-28T03:20:00.990Z level=info logger=machine event=x a=1",
        "ts=2025-11-28T03:20:01.002Z level=info logger=machine event=x a=1",
    ]


class _Stalled(io.StringIO):
    """A stream whose writes block until `go` is set (a log reader that stopped reading)."""

    def __init__(self) -> None:
        super().__init__()
        self.go = threading.Event()
        self.entered = threading.Event()

    def write(self, text: str) -> int:
        self.entered.set()
        assert self.go.wait(10.0), "never released"
        return super().write(text)


def _logger(lines: LineQueue, stream: io.StringIO) -> tuple[logging.Logger, LineWriter]:
    writer = LineWriter(lines, stream)
    writer.start()
    logger = logging.getLogger(f"test-logfmt-{id(lines)}")
    logger.propagate = False
    logger.handlers[:] = [LineHandler(lines)]  # type: ignore[arg-type]
    logger.setLevel(logging.INFO)
    return logger, writer


def test_a_line_says_what_its_arguments_were_when_it_was_logged() -> None:
    lines, stream = LineQueue(), io.StringIO()
    logger, writer = _logger(lines, stream)
    state = ["IDLE"]
    logger.info("event=x state=%s", state)
    state[0] = "HOMING"  # changed before the writer formats the line
    try:
        raise ValueError("boom")
    except ValueError:
        logger.exception("event=failed")
    writer.stop()
    text = stream.getvalue().splitlines()
    assert text[0].endswith("event=x state=['IDLE']")
    assert "event=failed traceback='Traceback" in text[1] and "ValueError: boom" in text[1]


def test_a_stalled_reader_never_blocks_the_logger_and_the_lost_lines_are_counted() -> None:
    lines, stream = LineQueue(capacity=100), _Stalled()
    logger, writer = _logger(lines, stream)
    # The reader stops with the writer inside its write (on a busy host the writer could
    # otherwise take a second batch before it blocks: the loss is then told in two parts).
    logger.info("event=first")
    assert stream.entered.wait(10.0)
    started = time.monotonic()
    for i in range(1000):
        logger.info("event=n i=%d", i)
    assert time.monotonic() - started < 5.0  # each call returned although nothing was written
    # The writer holds at most one batch (here the whole queue) in its write.
    assert lines.dropped >= 1000 - 2 * 100
    dropped = lines.dropped
    stream.go.set()
    deadline = time.monotonic() + 5.0
    while lines.queued and time.monotonic() < deadline:  # the writer catches up
        time.sleep(0.001)
    logger.info("event=n i=%d", 1000)  # the first line queued after the loss
    writer.stop()
    text = stream.getvalue().splitlines()
    kept = [int(line.rsplit("i=", 1)[1]) for line in text if "event=n" in line]
    assert kept == [*range(1000 - dropped), 1000]
    # The count stands where the lines went missing: after those kept, before the next one.
    assert "event=log_lines_dropped" in text[-2] and f"count={dropped} " in text[-2]


def test_the_exit_flush_writes_every_queued_line_and_never_hangs_on_a_stalled_reader() -> None:
    lines, stream = LineQueue(), io.StringIO()
    logger, writer = _logger(lines, stream)
    for i in range(500):
        logger.info("event=n i=%d", i)
    writer.stop()  # what flush_logs does at exit: the sentinel goes after every queued line
    assert len(stream.getvalue().splitlines()) == 500

    stalled = _Stalled()
    logger, writer = _logger(LineQueue(), stalled)
    logger.info("event=stuck")
    logfmt._writer = writer
    started = time.monotonic()
    logfmt.flush_logs(timeout=0.2)
    assert time.monotonic() - started < 2.0
    assert logfmt._writer is None
    stalled.go.set()


class _Kept(LineQueue):
    """A queue that keeps what kind of thing each queued item was."""

    def __init__(self) -> None:
        super().__init__()
        self.kinds: list[str] = []

    def put_nowait(self, record: logfmt.Item) -> None:
        self.kinds.append(type(record).__name__)
        super().put_nowait(record)


class _Counted(io.StringIO):
    """A stream that counts its writes."""

    writes = 0

    def write(self, text: str) -> int:
        self.writes += 1
        return super().write(text)


def test_a_burst_of_lines_is_written_in_one_write_per_batch() -> None:
    lines, stream = LineQueue(), _Counted()
    logger, writer = _logger(lines, stream)
    for i in range(200):
        logger.info("event=n i=%d", i)
    writer.stop()
    text = stream.getvalue().splitlines()
    assert [int(line.rsplit("i=", 1)[1]) for line in text] == list(range(200))
    assert stream.writes <= 200 // logfmt.WRITE_MAX + 2  # not one per line


def test_a_line_made_as_text_reads_as_the_same_line_made_from_a_record(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    lines, stream = _Kept(), io.StringIO()
    logger, writer = _logger(lines, stream)
    monkeypatch.setattr(logfmt, "_handler", logger.handlers[0])
    logger.info("%s", "event=command tx=a code=OK")
    logfmt.info(logger, "event=command tx=a code=OK")
    writer.stop()
    assert lines.kinds == ["LogRecord", "str", "NoneType"]  # the second made no record
    record_line, text_line = stream.getvalue().splitlines()
    stamp = r"ts=\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z"
    for line in (record_line, text_line):
        assert re.fullmatch(
            stamp + f" level=info logger={logger.name} event=command tx=a code=OK", line
        )


def test_a_line_made_as_text_goes_as_a_record_where_another_handler_or_a_filter_would_see_it(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    lines, stream = _Kept(), io.StringIO()
    logger, writer = _logger(lines, stream)
    monkeypatch.setattr(logfmt, "_handler", logger.handlers[0])
    logger.propagate = True  # pytest's capture sits at the root
    with caplog.at_level(logging.INFO):
        logfmt.info(logger, "event=a value=100%s")
    logger.propagate = False
    seen: list[str] = []

    def look(record: logging.LogRecord) -> bool:
        seen.append(record.getMessage())
        return True

    logger.addFilter(look)
    logfmt.info(logger, "event=b")
    logger.filters.clear()
    logger.setLevel(logging.WARNING)
    logfmt.info(logger, "event=c")  # below the level: neither a line nor a record
    writer.stop()
    assert [r.getMessage() for r in caplog.records] == ["event=a value=100%s"]
    assert seen == ["event=b"]
    assert lines.kinds == ["LogRecord", "LogRecord", "NoneType"]
    assert [line.split(" ", 3)[3] for line in stream.getvalue().splitlines()] == [
        "event=a value=100%s",
        "event=b",
    ]


def test_lines_made_by_another_process_go_out_whole_and_in_order_with_the_daemons(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The history process's lines (`put_text`, service/adapters/history.py) are queued as one
    item beside the daemon's own, so a batch of them is never split by another line."""
    lines, stream = LineQueue(), io.StringIO()
    logger, writer = _logger(lines, stream)
    monkeypatch.setattr(logfmt, "_handler", logger.handlers[0])
    logger.info("event=before")
    logfmt.put_text(
        "ts=x level=info logger=machine event=a\nts=y level=info logger=machine event=b\n"
    )
    logger.info("event=after")
    writer.stop()
    events = [line.rsplit("event=", 1)[1] for line in stream.getvalue().splitlines()]
    assert events == ["before", "a", "b", "after"]
    assert lines.queued == 0 and lines.dropped == 0
