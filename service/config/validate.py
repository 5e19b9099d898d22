"""The config check: findings `{category, severity, path, message}`, as a soft PLC reports them.

The file read, the schema's findings in the check's words, then the rules across fields
(service/config/rules.py); the findings and their report are made in service/config/report.py.
"""

from __future__ import annotations

import copy
import datetime as dt
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from ride_machine.schema.codec import json_pointer
from ride_machine.schema.findings import Finding, Findings

from .host import realtime_findings
from .model import HalBackend, MachineConfig, read_toml
from .report import Category, error, finding_line, findings_of, one_error, show
from .rules import MIN_RELIABLE_PERIOD_S, semantic_findings

__all__ = [
    "MIN_RELIABLE_PERIOD_S",
    "Category",
    "finding_line",
    "findings_of",
    "hardware_findings",
    "one_error",
    "read_file",
    "semantic_findings",
    "validate_data",
]
"""The check as the rest of the daemon uses it (findings and rules are made next door)."""

_RANGE_TYPES = {
    "greater_than",
    "greater_than_equal",
    "less_than",
    "less_than_equal",
    "finite_number",
    "string_too_short",
    "string_too_long",
    "string_pattern_mismatch",
    "too_short",
    "too_long",
    "enum",
    "literal_error",
}


def _schema_findings(exc: ValidationError) -> list[Finding]:
    out = []
    for err in exc.errors(include_url=False):
        kind = err["type"]
        if kind == "extra_forbidden":
            category, message = Category.UNKNOWN_KEY, "unknown key (not part of the machine config)"
        elif kind == "missing":
            category, message = Category.MISSING_KEY, err["msg"]
        elif kind == "hal_backend":  # [hal.<name>] for no registered backend
            category, message = Category.UNKNOWN_KEY, err["msg"]
        elif kind in _RANGE_TYPES:
            category, message = Category.OUT_OF_RANGE, err["msg"]
        else:
            category, message = Category.WRONG_TYPE, err["msg"]
        path = json_pointer(err["loc"])
        limits = {k: v for k, v in (err.get("ctx") or {}).items() if k in _LIMIT_KEYS}
        out.append(
            error(
                category,
                path,
                f"{message}; got {show(err.get('input'))}",
                type=kind,
                value=err.get("input"),
                **limits,
            )
        )
    return out


_LIMIT_KEYS = {"gt", "ge", "lt", "le", "min_length", "max_length", "pattern", "expected"}


def _unrepresentable(data: Any, loc: tuple[str | int, ...] = ()) -> Iterator[Finding]:
    """NaN/±inf slip past one-sided bounds and TOML dates fit no field: report them by path."""
    if isinstance(data, float) and not math.isfinite(data):
        yield error(
            Category.OUT_OF_RANGE, json_pointer(loc), f"must be a finite number; got {data}"
        )
    elif isinstance(data, dt.date | dt.time):
        yield error(
            Category.WRONG_TYPE, json_pointer(loc), f"a date/time fits no field; got {data}"
        )
    elif isinstance(data, dict):
        for key, value in data.items():
            yield from _unrepresentable(value, (*loc, str(key)))
    elif isinstance(data, list):
        for i, value in enumerate(data):
            yield from _unrepresentable(value, (*loc, i))


def _as_json(data: dict[str, Any]) -> str:
    # Dates are already reported; None keeps them failing validation at their own path.
    return json.dumps(data, default=lambda _: None, allow_nan=True)


def validate_data(data: dict[str, Any]) -> tuple[MachineConfig | None, Findings]:
    """Validate raw config data; the model is None when any error was found."""
    if not isinstance(data, dict):
        return None, findings_of(
            [error(Category.WRONG_TYPE, "", f"expected a table/object, got {show(data)}")]
        )
    odd = list(_unrepresentable(data))
    try:
        # Strict JSON mode: a string "0.01" for a float is a mistake to report, not to
        # coerce, while enums still take their string values as a config file spells them.
        config = MachineConfig.model_validate_json(_as_json(data), strict=True)
    except ValidationError as exc:
        # A NaN or a date is reported once, in its own words, not again as a schema error.
        known = {f.path for f in odd}
        found = odd + [f for f in _schema_findings(exc) if f.path not in known]
        return None, findings_of(found + _checks_without(data, found))
    if odd:
        return None, findings_of(odd + _checks_without(data, odd))
    report = findings_of(semantic_findings(config))
    return (config if report.ok else None), report


def _checks_without(data: dict[str, Any], bad: list[Finding]) -> list[Finding]:
    """The cross-field checks with every bad value left at its default, so that one run
    reports every finding; a check on a path already reported is not repeated."""
    repaired = copy.deepcopy(data)
    for f in bad:
        _drop(repaired, f.path)
    try:
        config = MachineConfig.model_validate_json(_as_json(repaired), strict=True)
    except ValidationError:
        return []  # could not isolate the bad values: the schema findings stand alone
    reported = {f.path for f in bad}
    return [f for f in semantic_findings(config) if f.path not in reported]


def _drop(data: dict[str, Any], pointer: str) -> None:
    parts = [p.replace("~1", "/").replace("~0", "~") for p in pointer.split("/")[1:]]
    node: Any = data
    for part in parts[:-1]:
        node = node.get(part) if isinstance(node, dict) else None
    if parts and isinstance(node, dict):
        node.pop(parts[-1], None)


def read_file(path: Path) -> tuple[dict[str, Any] | None, Findings]:
    """The raw TOML of a config file, or None and the one finding that says why not."""
    try:
        return read_toml(path), findings_of([])
    except FileNotFoundError:
        return None, one_error(Category.FILE, f"{path}: no such file")
    except IsADirectoryError:
        return None, one_error(Category.FILE, f"{path}: is a directory")
    except OSError as exc:
        return None, one_error(Category.FILE, f"{path}: cannot read ({exc.strerror})")
    except ValueError as exc:  # tomllib.TOMLDecodeError, UnicodeDecodeError
        return None, one_error(Category.SYNTAX, f"{path}: not valid TOML: {exc}")


def hardware_findings(config: MachineConfig) -> list[Finding]:
    """What the chosen backend finds on this host (piCtory config, process image, IO names),
    and whether the host grants `loop.rt_priority` (service/config/host.py).

    Not part of `validate_data`: it reads files of the host, and `--hal` may pick another
    backend than the file does. `machine validate` adds it to the report; `machine run` and
    `machine supervise` run it (on the config with their overrides) before they start.
    """
    found = realtime_findings(config)
    if config.hal.backend is not HalBackend.REVPI:
        return found
    from ride_machine.hal.revpi import (
        check_revpi_io,  # only with that backend: it pulls in revpimodio2
    )

    revpi = config.hal.revpi
    return [*check_revpi_io(config.hal.iomap, revpi.configrsc, revpi.procimg), *found]
