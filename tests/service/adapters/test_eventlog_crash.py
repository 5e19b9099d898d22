"""Crash safety of the event log: SIGKILL at random moments never corrupts the database, and
what a kill loses is only the newest events (measured here, printed with `-s`)."""

from __future__ import annotations

import os
import random
import sqlite3
import sys
from pathlib import Path

import pytest

from ride_machine.service.adapters.eventlog import EVENTS_FILE
from tests.service.adapters import eventlog_crash_writer as writer
from tests.service.crash import CrashServer

KILLS = 200
BOUND_S = 120.0  # a bound so a hung child fails the test instead of hanging it, not a speed check


def _written(db: Path, first: int) -> list[int]:
    """The event indexes of this round that are in the database, after an integrity check."""
    conn = sqlite3.connect(db, timeout=5.0)
    try:
        [(check,)] = conn.execute("PRAGMA integrity_check").fetchall()
        assert check == "ok", check
        rows = conn.execute(
            "SELECT cycle FROM events WHERE cycle >= ? ORDER BY seq", (first,)
        ).fetchall()
        seqs = conn.execute("SELECT seq FROM events ORDER BY seq").fetchall()
    finally:
        conn.close()
    assert [s for (s,) in seqs] == sorted({s for (s,) in seqs})  # seq only grows
    return [c for (c,) in rows]


@pytest.mark.hazard("H40")
@pytest.mark.integration
def test_sigkill_never_corrupts_the_event_log_and_loses_only_the_newest(tmp_path: Path) -> None:
    seed = int.from_bytes(os.urandom(4), "big")
    rng = random.Random(seed)
    missing: list[int] = []
    argv = [sys.executable, "-m", writer.__name__, str(tmp_path)]
    with CrashServer(argv, "e", BOUND_S) as server:
        start = 1
        for _ in range(KILLS):
            emitted = server.kill_round(start, rng.randint(1, 40), rng.uniform(0.0, 0.003))
            got = _written(tmp_path / EVENTS_FILE, start)
            # Batches commit whole and in order: what survived is a gap-free prefix.
            assert got == list(range(start, start + len(got))), (start, got[:5], got[-5:])
            last = got[-1] if got else start - 1
            missing.append(max(0, emitted - last))
            start = max(emitted, last) + 1
    settings = writer.SETTINGS
    worst = max(missing)
    print(
        f"seed={seed} kills={KILLS} pace_s={writer.PACE_S} missing_max={worst}"
        f" missing_mean={sum(missing) / len(missing):.2f}"
        f" lossless_kills={missing.count(0)}"
    )
    assert len(missing) == KILLS
    # The bound by construction: what was queued plus the batch being written.
    assert worst <= settings.queue_capacity + settings.batch_max
    assert missing.count(0) < KILLS  # some kills did land with events still on their way
