"""Crash safety of the event log: SIGKILL at random moments never corrupts the database, and
what a kill loses is only the newest events (measured here, printed with `-s`)."""

from __future__ import annotations

import os
import random
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.eventlog import EVENTS_FILE
from tests.procs import REPO
from tests.service import eventlog_crash_writer as writer
from tests.service.test_persist_crash import Lines

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


@pytest.mark.integration
def test_sigkill_never_corrupts_the_event_log_and_loses_only_the_newest(tmp_path: Path) -> None:
    seed = int.from_bytes(os.urandom(4), "big")
    rng = random.Random(seed)
    proc = subprocess.Popen(
        [sys.executable, "-m", writer.__name__, str(tmp_path)],
        cwd=REPO,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    assert proc.stdin is not None
    lines = Lines(proc, time.monotonic() + BOUND_S)
    pid: int | None = None
    missing: list[int] = []
    try:
        lines.word("ready")
        start = 1
        for _ in range(KILLS):
            proc.stdin.write(f"go {start}\n".encode())
            proc.stdin.flush()
            pid = lines.word("pid")
            emitted = start - 1
            for _ in range(rng.randint(1, 40)):
                emitted = lines.word("e")
            time.sleep(rng.uniform(0.0, 0.003))  # picks the kill moment; waits for nothing
            os.kill(pid, 9)
            while (line := lines.next()) != f"reaped {pid}":
                emitted = int(line.removeprefix("e "))  # queued before the kill landed
            pid = None
            got = _written(tmp_path / EVENTS_FILE, start)
            # Batches commit whole and in order: what survived is a gap-free prefix.
            assert got == list(range(start, start + len(got))), (start, got[:5], got[-5:])
            last = got[-1] if got else start - 1
            missing.append(max(0, emitted - last))
            start = max(emitted, last) + 1
    finally:
        if pid is not None:
            os.kill(pid, 9)
        proc.stdin.close()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
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
