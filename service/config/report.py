"""The config check's findings: their categories, one finding made, the report of many, and the
line a finding is printed as."""

from __future__ import annotations

import math
from enum import StrEnum
from typing import Any

from ride_machine.schema.findings import Finding, Findings, Severity


class Category(StrEnum):
    """What kind of problem a finding reports; stable strings that scripts may match on."""

    FILE = "file"
    SYNTAX = "syntax"
    UNKNOWN_KEY = "unknown_key"
    MISSING_KEY = "missing_key"
    WRONG_TYPE = "wrong_type"
    OUT_OF_RANGE = "out_of_range"
    IO_CONFLICT = "io_conflict"
    SCAN_PERIOD = "scan_period"
    TIMEOUT = "timeout"
    CALIBRATION = "calibration"
    SUPERVISION = "supervision"
    SIMULATOR = "simulator"
    SESSION = "session"
    BUS = "bus"
    EVENTS = "events"
    HAL = "hal"
    REALTIME = "realtime"
    MORE = "more"
    """Not a problem of its own: how many findings a capped report left out (`at_most`)."""


def _finding(
    severity: Severity, category: Category, path: str, message: str, extra: dict[str, Any]
) -> Finding:
    return Finding(
        category=category.value,
        severity=severity,
        path=path,
        message=message,
        extra={k: _scalar(v) for k, v in extra.items()},
    )


def error(category: Category, path: str, message: str, **extra: Any) -> Finding:
    """A finding that stops the config from being used; `extra`: values a script may read."""
    return _finding(Severity.ERROR, category, path, message, extra)


def warning(category: Category, path: str, message: str, **extra: Any) -> Finding:
    """A finding said, the config used all the same."""
    return _finding(Severity.WARNING, category, path, message, extra)


def _scalar(value: Any) -> bool | int | float | str | None:
    """A JSON-safe scalar for `Finding.extra` (other values as their short repr)."""
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    return show(value)


def show(value: Any) -> str:
    """A value as a message shows it: its repr, cut to 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def findings_of(items: list[Finding]) -> Findings:
    """The report: `ok` is false when any finding is an error."""
    return Findings(ok=not any(f.severity is Severity.ERROR for f in items), findings=items)


def at_most(report: Findings, limit: int) -> Findings:
    """`report` with no more than `limit` findings, errors first, and one more finding that says
    how many were left out (an error if any of them is); `ok` is the whole report's."""
    found = report.findings
    if len(found) <= limit:
        return report
    kept = sorted(found, key=lambda f: f.severity is not Severity.ERROR)
    left = kept[limit:]
    said = error if any(f.severity is Severity.ERROR for f in left) else warning
    note = said(
        Category.MORE,
        "",
        f"{len(left)} more findings not listed here (the first {limit} are); `machine validate`"
        " on the file lists every one",
        more=len(left),
    )
    return Findings(ok=report.ok, findings=[*kept[:limit], note])


def one_error(category: Category, message: str, path: str = "") -> Findings:
    """A report of one error (a file that cannot be read, a backend that cannot open)."""
    return findings_of([error(category, path, message)])


def finding_line(source: str, f: Finding) -> str:
    """One finding as `machine run`, `supervise` and the config loader print it on stderr."""
    return f"{source}: {f.severity}: {f.category} at {f.path or '/'}: {f.message}"
