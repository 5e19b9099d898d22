"""docs/seeds.md maps the seed documents to files, keys and tests: every path and test it names
exists, and every seed section heading is there."""

from __future__ import annotations

import re
from pathlib import Path

from ride_machine.schema.keys import KEYS, match

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "seeds.md"


def _cells() -> list[str]:
    rows = [ln for ln in DOC.read_text().splitlines() if ln.startswith("| ") and "---" not in ln]
    return [cell for row in rows for cell in row.split(" | ")]


def test_every_seed_has_its_table() -> None:
    text = DOC.read_text()
    for seed in ("## 001", "## 000", "## 002", "## 004"):
        assert seed in text


def test_every_named_test_and_file_exists() -> None:
    checked = 0
    for cell in _cells():
        last: Path | None = None
        for ref in re.findall(r"`([^`]+)`", cell):
            path_part, _, test = ref.partition("::")
            if path_part:
                if not re.fullmatch(
                    r"(tests|service|schema|hal|rider|docs|bench)/[\w./-]+", path_part
                ):
                    continue
                last = ROOT / path_part.split(" ")[0]
                assert last.exists(), f"docs/seeds.md names {path_part}, which does not exist"
                checked += 1
            if test:
                assert last is not None and last.suffix == ".py", ref
                assert re.search(rf"^def {re.escape(test)}\(", last.read_text(), re.M), (
                    f"docs/seeds.md names {last.relative_to(ROOT)}::{test}, which does not exist"
                )
                checked += 1
    assert checked > 80


def test_named_keys_are_in_the_key_table() -> None:
    rows = [ln.split(" | ") for ln in DOC.read_text().splitlines() if ln.startswith("| ")]
    keys = [
        ref
        for row in rows
        if len(row) == 5 and "---" not in row[2] and "seed-a" not in row[2]
        for ref in re.findall(r"`([^`]+)`", row[2])
    ]
    assert len(keys) > 20
    for key in keys:
        if "/" not in key or " " in key:  # a field of a record (`rotate_deg`), a top key
            continue
        if "*" in key:  # a wildcard: some key of the table must fall under it
            pattern = re.escape(key).replace(r"\*\*", ".+").replace(r"\*", "[^/]+")
            assert any(re.fullmatch(pattern, spec.key) for spec in KEYS), key
            continue
        assert match(re.sub(r"<[^>]+>", "x", key)) is not None, key
