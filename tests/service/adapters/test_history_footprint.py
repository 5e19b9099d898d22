"""The history process stays small: it loads neither pydantic nor Zenoh (the wire models were
half of its resident memory, bench.rss_soak), and what it makes without them (its settings, a
command's event, its own `storage_failed` and `events_dropped` records) is what the models
make."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from ride_machine.schema.events import DroppedEvent, StorageEvent, WatchdogEvent
from ride_machine.service.adapters.eventdb import dropped_row, storage_failed_row
from ride_machine.service.adapters.eventlog import EVENTS_FILE, as_row
from ride_machine.service.adapters.history import HistoryProcess
from ride_machine.service.adapters.history_writer import WriterSettings
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.held import Held, LogLine
from tests.procs import REPO
from tests.service.adapters.eventlog_support import FLUSH_S, T0, facts, note

HEAVY = ("pydantic", "pydantic_core", "zenoh")
"""What the history process must not load."""
NEEDLESS = ("ctypes", "logging.handlers")
"""Modules it has no use for, which the daemon's shared code brought in (~1.5 MiB together):
`ctypes` for thread names, `logging.handlers` for the log handler's base class."""


def test_the_running_history_process_maps_no_pydantic_and_no_zenoh(tmp_path: Path) -> None:
    """Its memory map once it has made and written commands and events, and pruned: the
    compiled cores of pydantic and of Zenoh are mapped from the moment either is imported."""
    log = HistoryProcess(tmp_path / EVENTS_FILE, "m1", EventsSection(prune_every_s=0.1))
    log.start()
    try:
        made = facts("tx-1")
        assert log.defer(Held([made, note(1.0)], T0, 1, LogLine(made)))
        log.emit(WatchdogEvent(stalled_s=0.1), T0, 2)
        assert log.flush(FLUSH_S)
        assert log.written == 3
        proc = log._proc
        assert proc is not None
        maps = Path(f"/proc/{proc.pid}/maps").read_text()
    finally:
        log.close()
    assert [name for name in HEAVY if f"/{name}/" in maps] == []


_PROBE = """
import sys, tempfile, time
from pathlib import Path
from ride_machine.service.adapters import history_writer as w
from ride_machine.service.adapters.history_pipe import COMMAND, LINE, MADE

class Pipe:
    def send(self, message):
        pass

settings = w.WriterSettings(16, 8, 1.0, 1.0, 1.0, 1.0, 0.1)
facts = ("home", "tx-1", "r1", True, "RESP_HOME_ACCEPTED", "", "HOMING", False, 1.0, None, None)
w.name_os_thread("history")
w.setup_logging("info", stream=sys.stderr)
with tempfile.TemporaryDirectory() as tmp:
    writer = w._Writer(Pipe(), Path(tmp) / "events.db", "m1", settings)
    writer.start()
    writer.record_failure("the disk", 3)
    items = ((COMMAND, time.time(), 1, facts, True), (MADE, "state", "{}", time.time(), 2))
    writer.receive(w.make_rows(items + ((LINE, "event=command tx=tx-0"),)), 2)
    assert writer.flush(10.0) and writer.written == 4, writer.status()
    writer.writer.prune(time.time(), lambda: None)
    writer.close()
w.flush_logs()
print(sorted({name.split(".")[0] for name in sys.modules} & {HEAVY!r}))
print(sorted(set(sys.modules) & {NEEDLESS!r}))
"""


def test_the_history_writers_code_imports_no_pydantic_no_zenoh_and_nothing_needless() -> None:
    """Its entry point's module, run through its thread's name, its logging, a command, a
    line, a `storage_failed` and an `events_dropped` record, retention and the stop, in a
    fresh interpreter."""
    probe = textwrap.dedent(_PROBE).replace("{HEAVY!r}", repr(set(HEAVY)))
    probe = probe.replace("{NEEDLESS!r}", repr(set(NEEDLESS)))
    out = subprocess.run(
        [sys.executable, "-c", probe],
        check=False,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-2:] == ["[]", "[]"]


def test_the_rows_it_makes_itself_are_the_models_rows() -> None:
    error = 'cannot write "events.db": disk full — é\n'
    assert storage_failed_row(error, 7, T0) == as_row(
        StorageEvent(what="events", error=error, lost=7), T0, None
    )
    assert dropped_row(12, T0) == as_row(DroppedEvent(count=12), T0, None)


def test_its_settings_are_the_daemons_events_section() -> None:
    section = EventsSection(queue_capacity=100, batch_max=7, max_mb=3.0, prune_every_s=2.0)
    settings = WriterSettings.from_json(section.model_dump_json())
    assert settings._asdict() == {name: getattr(section, name) for name in settings._fields}
