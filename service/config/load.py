"""The one way a machine config is loaded: file (or defaults), then overrides, then validation.

`machine run`, `machine supervise`, `machine validate` and the `config/validate` key all come
here, so a value given on the command line (`--period`, `--id`, …) meets exactly the checks a
file value meets, and the config that runs is the one that was validated.
"""

from __future__ import annotations

import copy
import json
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ride_machine.schema.findings import Finding, Findings

from .model import MachineConfig
from .report import at_most
from .validate import (
    Category,
    findings_of,
    one_error,
    read_file,
    semantic_findings,
    validate_data,
)

Overrides = Mapping[str, Any]
"""Config field (JSON pointer, e.g. `/loop/period_s`) → value that replaces the file's."""

MAX_FINDINGS = 100
"""Findings a candidate's check replies with at most (a 64 KiB candidate made 6611 of them, a
reply of 1.1 MB: past what a Rider reads); one more says how many were left out."""


def load(
    path: Path | None, overrides: Overrides | None = None
) -> tuple[MachineConfig | None, Findings]:
    """The validated config with `overrides` applied, or None; every finding either way."""
    if path is None:
        data: dict[str, Any] = {}
    else:
        raw, findings = read_file(path)
        if raw is None:
            return None, findings
        data = raw
    return load_data(data, overrides)


def load_data(
    data: dict[str, Any], overrides: Overrides | None = None
) -> tuple[MachineConfig | None, Findings]:
    """As `load`, for config data already parsed (a candidate sent on the bus)."""
    try:
        merged = copy.deepcopy(data)
        for pointer, value in (overrides or {}).items():
            parts = pointer.strip("/").split("/")
            node = merged
            for part in parts[:-1]:
                child = node.get(part)
                if not isinstance(child, dict):
                    child = node[part] = {}
                node = child
            node[parts[-1]] = value
        return validate_data(merged)
    except RecursionError:
        # Tables or arrays nested some hundreds deep (a kilobyte of JSON) parse, but neither
        # the copy nor the check can recurse that far: a finding, not an unanswered query.
        return None, one_error(
            Category.SYNTAX, "config is nested too deeply to be checked (a few levels at most)"
        )


def override_source(f: Finding, options: Mapping[str, str], default: str) -> str:
    """Where a finding's value came from: the command-line option that set it, else `default`."""
    return options.get(f.path, default)


def check_candidate(running: MachineConfig, candidate: bytes | None) -> Findings:
    """Findings for the running config, or for a candidate sent as TOML or JSON text."""
    if candidate is None:
        return findings_of(semantic_findings(running))
    try:
        text = candidate.decode()
        data = json.loads(text) if text.lstrip().startswith("{") else tomllib.loads(text)
    except (ValueError, RecursionError) as exc:  # JSON, TOML and UTF-8 errors
        return one_error(
            Category.SYNTAX, f"candidate config is neither TOML nor a JSON object: {exc}"
        )
    if not isinstance(data, dict):
        return validate_data(data)[1]  # one finding: "expected a table/object, got …"
    return at_most(load_data(data)[1], MAX_FINDINGS)
