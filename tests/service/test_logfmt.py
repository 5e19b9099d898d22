"""Structured log lines: the timestamp stays right although it is formatted once per second."""

from __future__ import annotations

import logging

from service.logfmt import KeyValueFormatter


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
