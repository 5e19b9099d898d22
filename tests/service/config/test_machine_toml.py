"""The shipped example config: valid, on the simulator, complete, commented, and documented."""

from __future__ import annotations

import re
from pathlib import Path

from pydantic import BaseModel

from ride_machine.service.config.load import load
from ride_machine.service.config.model import HalBackend, MachineConfig
from ride_machine.service.config.validate import Category

ROOT = Path(__file__).resolve().parents[3]
EXAMPLE = ROOT / "machine.toml"
DOC = ROOT / "docs" / "config.md"


def tables(model: type[BaseModel], prefix: str = "") -> dict[str, list[str]]:
    """Every TOML table of the config (dotted name) → its keys as a file spells them."""
    out: dict[str, list[str]] = {prefix: []}
    for name, info in model.model_fields.items():
        key = info.alias or name
        sub = info.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            out.update(tables(sub, f"{prefix}.{key}" if prefix else key))
        else:
            out[prefix].append(key)
    return out


def sections(text: str) -> dict[str, str]:
    """The text of each table in a TOML file (`""` = before the first header)."""
    out, name = {"": ""}, ""
    for line in text.splitlines():
        header = re.fullmatch(r"\[([\w.]+)\]\s*(#.*)?", line.strip())
        if header:
            name = header.group(1)
            out[name] = ""
        else:
            out[name] += line + "\n"
    return out


def test_example_validates_without_any_finding() -> None:
    config, report = load(EXAMPLE)
    assert config is not None, report
    assert report.findings == []


def test_example_runs_on_the_simulator_and_holds_the_project_defaults() -> None:
    config, _ = load(EXAMPLE)
    assert config is not None
    assert config.hal.backend is HalBackend.SIM
    # The header says a key left out takes the default "shown here": keep that true.
    assert config == MachineConfig()


def test_make_run_uses_the_example() -> None:
    assert "--config machine.toml" in (ROOT / "Makefile").read_text()


def test_example_spells_out_every_key_and_comments_every_table() -> None:
    text = EXAMPLE.read_text()
    found = sections(text)
    lines = text.splitlines()
    for table, keys in tables(MachineConfig).items():
        assert table in found, f"[{table}] is missing from machine.toml"
        for key in keys:
            # A key without a TOML spelling (None) appears commented out, with an example.
            assert re.search(rf"^#?\s*{key}\s*=", found[table], re.M), f"{table}.{key} missing"
        if table:
            at = lines.index(next(x for x in lines if x.strip().startswith(f"[{table}]")))
            assert lines[at - 1].startswith("#"), f"[{table}] has no comment above it"


def test_docs_describe_every_key_and_every_finding_category() -> None:
    doc = DOC.read_text()
    for table, keys in tables(MachineConfig).items():
        for key in keys:
            dotted = f"{table}.{key}" if table else key
            assert f"`{dotted}`" in doc, f"docs/config.md does not describe {dotted}"
    for category in Category:
        assert f"`{category.value}`" in doc, f"docs/config.md does not explain {category.value}"
