"""The soak script runs: a 15-second soak with one kill finishes, misses no reply and writes
its section."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.procs import run_module

pytestmark = pytest.mark.integration

BOUND_S = 180.0


def test_short_soak_misses_no_reply_and_writes_its_section(tmp_path: Path) -> None:
    out = tmp_path / "SOAK.md"
    text = run_module(
        "bench.soak", "--minutes", "0.25", "--kills", "1", "--out", out, timeout=BOUND_S
    )
    assert re.search(r"\*\*missed replies\*\*\s+0\s", text), text
    assert re.search(r"Rider connect/disconnect\s+[1-9]\d*\s+0 failed", text), text
    assert re.search(r"rides to DONE\s+[1-9]", text), text
    assert "world relays on after FAULT_HW: 0" in text
    written = out.read_text()
    assert "<!-- bench:soak -->" in written and "<!-- /bench:soak -->" in written
    assert "Memory (RSS)" in written
