"""`machine events export`: the event history as CSV or JSON lines, read from the database file.

Offline: it needs no running daemon and opens the database read-only, so it can run beside one.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sqlite3
import sys
import time
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path
from typing import TextIO

from ride_machine.common.event_words import describe
from ride_machine.schema.events import Event, query_of

from .eventdb import connect_readonly
from .eventlog import EVENTS_FILE
from .eventread import iter_events

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2

CSV_COLUMNS = ["seq", "time", "local_time", "cycle", "machine_id", "kind", "text", "details"]


def export_events(args: argparse.Namespace, data_dir: Path) -> int:
    try:
        query = query_of(args.since, args.until, args.kind, time.time())
    except ValueError as exc:
        print(f"machine: {exc}", file=sys.stderr)
        return EXIT_USAGE
    path = data_dir / EVENTS_FILE
    try:
        conn = connect_readonly(path)
    except (FileNotFoundError, sqlite3.Error) as exc:
        print(f"machine: {exc}", file=sys.stderr)
        return EXIT_FAILED
    try:
        events = iter_events(conn, query)
        if args.output is None:
            write(events, sys.stdout, args.format)
        else:
            with args.output.open("w", newline="") as out:
                write(events, out, args.format)
    except sqlite3.Error as exc:
        print(f"machine: reading {path} failed: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except BrokenPipeError:
        # `machine events export | head`: the reader has gone; stop quietly, and keep the
        # interpreter's final flush of stdout from raising again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except OSError as exc:  # -o into a missing or read-only directory, a full disk
        print(
            f"machine: cannot write {exc.filename or args.output}: {exc.strerror}", file=sys.stderr
        )
        return EXIT_FAILED
    finally:
        conn.close()
    return EXIT_OK


def write(events: Iterable[Event], out: TextIO, fmt: str) -> None:
    """One event per line (jsonl), or a CSV row per event with the details as JSON."""
    if fmt == "jsonl":
        for event in events:
            out.write(event.model_dump_json() + "\n")
        return
    writer = csv.writer(out)
    writer.writerow(CSV_COLUMNS)
    for e in events:
        details = e.model_dump(mode="json")["details"]
        writer.writerow(
            [
                e.seq,
                f"{e.time:.6f}",
                datetime.fromtimestamp(e.time).isoformat(timespec="milliseconds"),
                "" if e.cycle is None else e.cycle,
                e.machine_id,
                e.kind,
                describe(e.details),
                json.dumps(details, separators=(",", ":")),
            ]
        )
