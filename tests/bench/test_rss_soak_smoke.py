"""The RSS soak runs: a few seconds of it finish, churn without a failed connect, count the
daemons' malloc arenas and write its section. No memory figure is asserted: that is what it
reports."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from ride_machine.service.supervision.malloc import MALLOC_ARENAS
from tests.procs import run_module

pytestmark = pytest.mark.integration

BOUND_S = 120.0


def test_short_rss_soak_churns_and_writes_its_section(tmp_path: Path) -> None:
    out = tmp_path / "B.md"
    text = run_module("bench.rss_soak", "--minutes", "0.1", "--out", out, timeout=BOUND_S)
    # Each churned process connected at least once, none failed (a failure shows its count).
    capped = f"daemon, Rider churn, malloc_arenas = {MALLOC_ARENAS}"
    for label in (
        capped,
        "daemon, Rider churn, glibc's default arenas",
        "bare Zenoh echo, same churn",
    ):
        row = re.search(rf"^{re.escape(label)}\s+([\d,]+)\s+(\S+)", text, re.MULTILINE)
        assert row is not None, text
        assert int(row.group(1).replace(",", "")) > 0 and not row.group(2).startswith("("), text
    bounded = re.search(rf"^{re.escape(capped)}\s.*\s(\d+)\s*$", text, re.MULTILINE)
    assert bounded is not None and int(bounded.group(1)) <= MALLOC_ARENAS, text
    written = out.read_text()
    assert "<!-- bench:rss_soak -->" in written and "<!-- /bench:rss_soak -->" in written
    assert "RSS growth after the warm-up" in written
