"""The event history at its size limit: what a prune costs with the safety record kept apart, and
what a daemon's start pays to read its recent answers back (issue 43).

A history file is filled past `[events] max_mb` with refused `check/home` commands (what a
command flood leaves) after a safety record (E-stops, faults, lost Riders) at its start. Then,
on that file, as the history's writer runs them (service/adapters/retention.py):

- **prune at the limit**: the prune that takes the file back under its limit (routine events
  only), its wall and CPU time and the rows it deleted, and that every safety event is kept;
- **prune, nothing to do**: the next one (every `prune_every_s`, 60 s by default);
- **recall at start**: `replay.recall` of the newest `bus.transaction_window` (4096) commands
  and their notices, which `machine run` does before its scan loop starts.
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bench.common import Options, Section, Table, Target, main_quiet, ms
from ride_machine.schema.codec import dump_json
from ride_machine.schema.events import (
    CommandEvent,
    EstopEvent,
    FaultEvent,
    KnownDetails,
    RiderEvent,
)
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.eventdb import connect
from ride_machine.service.adapters.eventlog import EVENTS_FILE
from ride_machine.service.adapters.replay import recall
from ride_machine.service.adapters.retention import SAFETY_KINDS, prune, used_bytes
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.commands.transactions import TransactionLog

T0 = 1_800_000_000.0
SAFETY_ROWS = 2000
"""A year of a busy machine's safety record, at the start of the file."""
INSERT_CHUNK = 5000


@dataclass
class Round:
    size_mb: float
    rows: int
    wall_s: float
    cpu_s: float
    deleted: int
    kept_safety: bool
    under_limit: bool
    idle_wall_s: float
    recall_s: float
    recalled: int


def _safety(i: int) -> KnownDetails:
    if i % 3 == 0:
        return EstopEvent(kind="estop_pressed", state=MachineState.RUNNING)
    if i % 3 == 1:
        return FaultEvent(kind="fault_raised", code="TILT_TIMEOUT", message="tilt did not move")
    return RiderEvent(kind="rider_lost", rider=f"bay1/{i:032x}", policy="pause", acted=True)


def _fill(path: Path, limit_mb: float) -> int:
    """The safety record, then refused commands until the file holds 1.2 × `limit_mb`."""
    conn = connect(path)
    rows = [
        ("m1", d.kind, dump_json(d), T0 + i) for i, d in enumerate(map(_safety, range(SAFETY_ROWS)))
    ]
    sql = "INSERT INTO events (machine_id, kind, details, time) VALUES (?, ?, ?, ?)"
    conn.executemany(sql, rows)
    n = 0
    while used_bytes(conn) < 1.2 * limit_mb * 1024 * 1024:
        chunk = []
        for _ in range(INSERT_CHUNK):
            n += 1
            event = CommandEvent(
                command="CheckHome",
                transaction_id=f"flood-{n}",
                rider="bay2/0123456789abcdef0123456789abcdef",
                accepted=True,
                code="RESP_CHECK",
                state=MachineState.IDLE,
            )
            chunk.append(("m1", event.kind, dump_json(event), T0 + SAFETY_ROWS + n / 1000))
        conn.execute("BEGIN")
        conn.executemany(sql, chunk)
        conn.execute("COMMIT")
    conn.close()
    return SAFETY_ROWS + n


def _round(limit_mb: float) -> Round:
    with tempfile.TemporaryDirectory(prefix="bench-retention-") as tmp:
        path = Path(tmp) / EVENTS_FILE
        rows = _fill(path, limit_mb)
        settings = EventsSection(max_mb=limit_mb)
        now = T0 + SAFETY_ROWS + rows / 1000 + 1
        with contextlib.closing(connect(path)) as conn:
            size = used_bytes(conn) / 1024 / 1024
            t0, c0 = time.perf_counter(), time.process_time()
            prune(conn, settings, now, lambda: None)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            under = used_bytes(conn) <= limit_mb * 1024 * 1024
            [(left,)] = conn.execute("SELECT COUNT(*) FROM events").fetchall()
            kinds = ",".join(f"'{k}'" for k in SAFETY_KINDS)
            [(safety,)] = conn.execute(f"SELECT COUNT(*) FROM events WHERE kind IN ({kinds})")
            t1 = time.perf_counter()
            prune(conn, settings, now, lambda: None)
            idle = time.perf_counter() - t1
        t2 = time.perf_counter()
        got = recall(path, "m1", 4096)
        log = TransactionLog(4096)  # what `machine run` fills with them
        for tid, command, packed in got.replies:
            log.remember(tid, command, packed)
        recall_s = time.perf_counter() - t2
    kept = safety == SAFETY_ROWS
    return Round(size, rows, wall, cpu, rows - left, kept, under, idle, recall_s, len(got.replies))


def run(opts: Options) -> Section:
    limits = opts.pick([4.0], [16.0, 64.0])
    section = Section("retention", "14. Event history: retention at the limit, recall at start")
    table = Table(
        "Prune and recall",
        [
            "max_mb",
            "file before",
            "rows",
            "prune: wall",
            "prune: CPU",
            "rows deleted",
            "safety kept",
            "prune, nothing to do",
            "recall 4096",
        ],
    )
    rounds = []
    for limit in limits:
        r = _round(limit)
        rounds.append(r)
        table.add(
            f"{limit:g}",
            f"{r.size_mb:.1f} MB",
            f"{r.rows:,}",
            ms(r.wall_s, 1),
            ms(r.cpu_s, 1),
            f"{r.deleted:,}",
            f"{'all' if r.kept_safety else 'NOT all'} {SAFETY_ROWS:,}",
            ms(r.idle_wall_s, 1),
            f"{ms(r.recall_s, 1)} ({r.recalled})",
        )
    section.tables.append(table)
    kept = sum(r.kept_safety for r in rounds)
    section.targets += [
        Target(
            "the safety record survives a prune at the limit",
            "every safety event kept",
            f"kept in {kept} of {len(rounds)} files",
            kept == len(rounds),
        ),
        Target(
            "a prune takes the file back under max_mb",
            "under max_mb",
            f"{sum(r.under_limit for r in rounds)} of {len(rounds)} files",
            all(r.under_limit for r in rounds),
        ),
        Target.at_most(
            "the start-up recall of 4096 commands",
            max(r.recall_s for r in rounds),
            1.0,
            lambda v: f"{v * 1000:.0f} ms",
        ),
    ]
    section.notes += [
        "One SQLite connection in this process, WAL, the file in a temporary directory (tmpfs"
        " or disk, as the host has it); the daemon runs the prune on its history writer (its"
        " own process by default), between batches, so a prune's time delays the writing of"
        " events, never the scan loop.",
        "The prune measures the average routine row once (a scan of the table) and deletes in"
        " chunks of 2000 rows down to 90 % of `max_mb`; the safety record (first in the file)"
        " is left alone.",
        "Recall: the newest 4096 `command` events (and `completion` events) read back, decoded"
        " into replies and recorded in a transaction log, as `machine run` does before its"
        " first scan (a start pays it once).",
    ]
    return section


if __name__ == "__main__":
    sys.exit(main_quiet("bench.retention", __doc__ or "", run))
