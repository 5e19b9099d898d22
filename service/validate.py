"""The config check: findings `{category, severity, path, message}`, as a soft PLC reports them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import ValidationError

from schema.codec import json_pointer
from schema.findings import Finding, Findings, Severity
from service.config import MachineConfig, read_toml


def _schema_findings(exc: ValidationError) -> list[Finding]:
    out = []
    for err in exc.errors(include_url=False):
        kind = err["type"]
        category = {
            "extra_forbidden": "unknown_key",
            "missing": "missing_key",
        }.get(kind, "out_of_range" if kind in _RANGE_TYPES else "wrong_type")
        out.append(
            Finding(
                category=category,
                severity=Severity.ERROR,
                path=json_pointer(err["loc"]),
                message=err["msg"],
            )
        )
    return out


_RANGE_TYPES = {
    "greater_than",
    "greater_than_equal",
    "less_than",
    "less_than_equal",
    "string_too_short",
    "string_too_long",
    "string_pattern_mismatch",
    "too_short",
    "too_long",
    "enum",
    "literal_error",
}


def semantic_findings(config: MachineConfig) -> list[Finding]:
    """Checks across fields that the schema alone cannot express."""
    out: list[Finding] = []
    iomap = config.hal.iomap.model_dump(by_alias=True, exclude={"estop_active_low"})
    seen: dict[str, str] = {}
    for name, channel in iomap.items():
        if channel in seen:
            out.append(
                Finding(
                    category="io_conflict",
                    severity=Severity.ERROR,
                    path=f"/hal/iomap/{name}",
                    message=f"channel {channel!r} is already used by {seen[channel]!r}",
                )
            )
        else:
            seen[channel] = name
    if config.tilt.min_deg >= config.tilt.max_deg:
        out.append(
            Finding(
                category="out_of_range",
                severity=Severity.ERROR,
                path="/tilt/min_deg",
                message=f"tilt.min_deg {config.tilt.min_deg:g} must be below"
                f" tilt.max_deg {config.tilt.max_deg:g}",
            )
        )
    if config.tilt.gain_min_counts_per_deg >= config.tilt.gain_max_counts_per_deg:
        out.append(
            Finding(
                category="out_of_range",
                severity=Severity.ERROR,
                path="/tilt/gain_min_counts_per_deg",
                message="tilt.gain_min_counts_per_deg must be below tilt.gain_max_counts_per_deg",
            )
        )
    return out


def validate_data(data: dict[str, Any]) -> tuple[MachineConfig | None, Findings]:
    """Validate raw config data; the model is None when any error was found."""
    try:
        config = MachineConfig.model_validate(data)
    except ValidationError as exc:
        return None, Findings(ok=False, findings=_schema_findings(exc))
    findings = semantic_findings(config)
    ok = not any(f.severity is Severity.ERROR for f in findings)
    return (config if ok else None), Findings(ok=ok, findings=findings)


def validate_file(path: Path) -> tuple[MachineConfig | None, Findings]:
    """Load and check a TOML config file; a file that does not parse is one finding."""
    try:
        data = read_toml(path)
    except FileNotFoundError:
        return None, _one("file", "", f"{path}: no such file")
    except OSError as exc:
        return None, _one("file", "", f"{path}: cannot read ({exc.strerror})")
    except ValueError as exc:  # tomllib.TOMLDecodeError, UnicodeDecodeError
        return None, _one("syntax", "", f"{path}: not valid TOML: {exc}")
    return validate_data(data)


def _one(category: str, path: str, message: str) -> Findings:
    return Findings(
        ok=False,
        findings=[Finding(category=category, severity=Severity.ERROR, path=path, message=message)],
    )
