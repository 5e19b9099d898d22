"""Structured logs: one `key=value` line per event."""

from __future__ import annotations

import logging
import sys
import time


class KeyValueFormatter(logging.Formatter):
    """`ts=... level=... logger=... event=...`: greppable and machine-parsable."""

    _second = -1
    _stamp = ""

    def format(self, record: logging.LogRecord) -> str:
        second = int(record.created)
        if second != self._second:  # one strftime per second, not per line (a line per command)
            self._stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(second))
            self._second = second
        ts = self._stamp
        line = (
            f"ts={ts}.{int(record.msecs):03d}Z level={record.levelname.lower()}"
            f" logger={record.name} {record.getMessage()}"
        )
        if record.exc_info:
            line += " traceback=" + repr(self.formatException(record.exc_info))
        return line


def setup_logging(level: str = "info") -> None:
    # The format names neither thread, process nor source line: don't look them up for every
    # record (the logging HOWTO's "Optimization"; a quarter of a command's log line).
    logging.logThreads = False
    logging.logProcesses = False
    logging.logMultiprocessing = False
    logging._srcfile = None
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(KeyValueFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
