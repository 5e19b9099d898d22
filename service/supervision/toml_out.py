"""The child daemon's config files: plain data as a TOML document, written owner-only."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ride_machine.service.core.storage.atomic import atomic_write

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def to_toml(data: Mapping[str, Any], prefix: str = "") -> str:
    """A TOML document of plain data (None values left out), for the child's config file."""
    lines: list[str] = []
    tables: list[tuple[str, Mapping[str, Any]]] = []
    for key, value in data.items():
        if value is None:
            continue
        if isinstance(value, Mapping):
            tables.append((f"{prefix}.{_key(key)}" if prefix else _key(key), value))
        else:
            lines.append(f"{_key(key)} = {_value(value)}")
    parts = ["\n".join(lines)] if lines else []
    parts += [f"[{name}]\n{to_toml(table, name)}" for name, table in tables]
    return "\n\n".join(p for p in parts if p.strip()) + "\n"


def _key(key: str) -> str:
    return key if _BARE_KEY.match(key) else json.dumps(key)


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a TOML basic string
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {type(value).__name__}")


def write_private(path: Path, text: str) -> None:
    """Owner-only (the child's zenoh config may carry what the user's file carries) and
    atomic: a child started meanwhile reads the old file or the new one, never half of it."""
    atomic_write(path, text.encode(), 0o600)
