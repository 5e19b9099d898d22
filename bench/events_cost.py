"""What the event history costs the scan loop: execution time, jitter and overruns, log off and on.

In-process, the real-time runner at 10 ms on the simulator, under a storm that makes events as
fast as an operator never would: commands at `COMMAND_RATE` per second (each one an event) and
the E-stop pressed or released every `ESTOP_EVERY_S` (three or four events each). Three modes,
alternated in the same run so the host's load hits them alike:

- **off**: the recorder runs but its sink discards everything (the loop's own share);
- **on**: the SQLite writer thread in a temporary data_dir;
- **on, disk stalled**: the same, while another connection holds the database locked, so the
  writer waits and its queue fills: events are dropped (and counted), the loop must not notice.
"""

from __future__ import annotations

import gc
import sqlite3
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from bench.common import Options, Section, Table, Target, main_quiet, ms
from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.history import HistoryProcess
from ride_machine.service.config.model import EventsSection, MachineConfig
from ride_machine.service.core.scan.loop import ScanLoop
from ride_machine.service.core.scan.machine import Machine
from ride_machine.service.core.scan.runner import RealtimeRunner
from ride_machine.service.core.scan.tasks import LoopCall, PendingCommand
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.scan.tuning import slice_process, tune_thread
from ride_machine.sim.hal import SimHal
from ride_machine.sim.settings import PhysicsParams

PERIOD_S = 0.010
COMMAND_RATE = 500.0
ESTOP_EVERY_S = 0.1
MODES = ("off", "on", "on, disk stalled")


@dataclass
class Result:
    mode: str
    seconds: float
    cycles: int
    exec_p50: float
    exec_p99: float
    exec_max: float
    jitter_p50: float
    jitter_p99: float
    jitter_max: float
    overruns: int
    missed: int
    commands: int
    written: int
    dropped: int
    lost: int


def _storm(loop: ScanLoop, hal: SimHal, stop: threading.Event) -> None:
    """Commands at COMMAND_RATE (a refused Pause and an accepted CheckHome, alternately) and
    the E-stop toggled every ESTOP_EVERY_S, both through the inbox as the bus would."""
    gap = 1.0 / COMMAND_RATE
    n = 0
    next_toggle = time.monotonic() + ESTOP_EVERY_S
    pressed = False

    def ignore(reply: Reply) -> None:
        pass

    while not stop.wait(gap):
        n += 1
        command = Command.PAUSE if n % 2 else Command.CHECK_HOME
        request = CommandRequest(transaction_id=f"b{n}")
        loop.inbox.put(PendingCommand(command, request, ignore))
        if time.monotonic() >= next_toggle:
            next_toggle += ESTOP_EVERY_S
            pressed = not pressed
            loop.inbox.put(LoopCall(_toggle(hal, pressed)))


def _toggle(hal: SimHal, pressed: bool) -> Callable[[ScanLoop, float], None]:
    def toggle(loop: ScanLoop, now: float) -> None:
        if pressed:
            hal.press_estop()
        else:
            hal.release_estop()

    return toggle


def one_run(mode: str, seconds: float, directory: Path) -> Result:
    config = MachineConfig()
    clock = time.monotonic
    hal = SimHal(clock, config.hal.iomap, PhysicsParams.model_validate(config.hal.sim))
    events: EventLog | None = None
    blocker: sqlite3.Connection | None = None
    if mode != "off":
        db = directory / f"{len(list(directory.iterdir()))}-{EVENTS_FILE}"
        kind = HistoryProcess if config.events.process else EventLog  # as the daemon does
        events = kind(db, config.machine.id, EventsSection())
        events.start()
        if mode == "on, disk stalled":
            blocker = sqlite3.connect(db, timeout=5.0)
            blocker.execute("BEGIN EXCLUSIVE")
    machine = Machine(config, hal, now=clock(), on_transition=None, events=events)
    stats = CycleStats(PERIOD_S, window=100_000, now=time.time())
    runner = RealtimeRunner(machine.loop, PERIOD_S, stats)

    def scan_thread() -> None:
        # As `machine run` does (the [loop] defaults): time slice, timer slack, gc.freeze().
        if config.loop.slice_ns is not None:
            slice_process(config.loop.slice_ns)
        tune_thread(config.loop.gc_freeze, config.loop.cpu, config.loop.rt_priority)
        runner.run()

    scan = threading.Thread(target=scan_thread, name="scan")
    stop = threading.Event()
    storm = threading.Thread(target=_storm, args=(machine.loop, hal, stop), name="storm")
    t0 = time.monotonic()
    scan.start()
    storm.start()
    try:
        time.sleep(seconds)
    finally:
        stop.set()
        storm.join(5.0)
        runner.stop()
        scan.join(5.0)
        if blocker is not None:
            blocker.rollback()
            blocker.close()
        if events is not None:
            events.flush(10.0)
            events.close()
        gc.unfreeze()  # the next run freezes its own start-up objects
    diag = stats.diag(time.time())
    return Result(
        mode=mode,
        seconds=time.monotonic() - t0,
        cycles=diag.cycles,
        exec_p50=diag.execution.p50,
        exec_p99=diag.execution.p99,
        exec_max=diag.execution.max,
        jitter_p50=diag.jitter.p50,
        jitter_p99=diag.jitter.p99,
        jitter_max=diag.jitter.max,
        overruns=diag.overruns,
        missed=diag.missed_cycles,
        commands=machine.loop.commands_handled,
        written=events.written if events is not None else 0,
        dropped=events.dropped if events is not None else 0,
        lost=events.lost if events is not None else 0,
    )


def run(opts: Options) -> Section:
    seconds = opts.pick(2.0, 20.0, 120.0)
    rounds = opts.pick(1, 2, 3)
    section = Section("events_cost", "6. Event history: cost to the scan loop")
    results: dict[str, list[Result]] = {m: [] for m in MODES}
    with tempfile.TemporaryDirectory(prefix="bench-events-") as tmp:
        for _ in range(rounds):
            for mode in MODES:
                results[mode].append(one_run(mode, seconds, Path(tmp)))
    table = Table(
        f"Scan loop at {PERIOD_S * 1000:g} ms under {COMMAND_RATE:g} commands/s and an E-stop"
        f" toggle every {ESTOP_EVERY_S * 1000:g} ms (ms; {rounds} × {seconds:g} s per mode,"
        " modes alternated)",
        [
            "event log",
            "cycles",
            "exec p50",
            "exec p99",
            "exec max",
            "jitter p50",
            "jitter p99",
            "jitter max",
            "overruns",
            "commands",
            "events written",
            "events dropped",
            "events lost",
        ],
    )
    merged = {mode: _merge(rs) for mode, rs in results.items()}
    for mode, r in merged.items():
        table.add(
            mode,
            r.cycles,
            ms(r.exec_p50),
            ms(r.exec_p99),
            ms(r.exec_max),
            ms(r.jitter_p50),
            ms(r.jitter_p99),
            ms(r.jitter_max),
            r.overruns,
            r.commands,
            r.written,
            r.dropped,
            r.lost,
        )
    section.tables.append(table)
    off, on, stalled = (merged[m] for m in MODES)
    section.targets += [
        Target.at_most("exec p99, log on − log off", on.exec_p99 - off.exec_p99, 0.0002, ms),
        Target.at_most("overruns with the log on", on.overruns, off.overruns + 1, str),
        Target.at_most("overruns with the disk stalled", stalled.overruns, off.overruns + 1, str),
    ]
    section.notes += [
        "Percentiles are of each mode's worst round (max over rounds); counts are summed.",
        "A stalled disk (the database locked by another connection for the whole run) holds the"
        " writer in SQLite's busy wait (`BUSY_TIMEOUT_S`, 1 s): each batch that still cannot"
        " be written is lost"
        " (counted, and recorded as a `storage_failed` event once the disk is back), and past"
        " the queue's 4096 events new ones are dropped (counted, recorded as `events_dropped`).",
        "Each command is one `command` event; each E-stop toggle makes `estop_pressed`, a state"
        " change and `estop_latched`, or `estop_released`.",
    ]
    return section


def _merge(rs: list[Result]) -> Result:
    """The worst percentiles and the summed counts over rounds."""
    return Result(
        mode=rs[0].mode,
        seconds=sum(r.seconds for r in rs),
        cycles=sum(r.cycles for r in rs),
        exec_p50=max(r.exec_p50 for r in rs),
        exec_p99=max(r.exec_p99 for r in rs),
        exec_max=max(r.exec_max for r in rs),
        jitter_p50=max(r.jitter_p50 for r in rs),
        jitter_p99=max(r.jitter_p99 for r in rs),
        jitter_max=max(r.jitter_max for r in rs),
        overruns=sum(r.overruns for r in rs),
        missed=sum(r.missed for r in rs),
        commands=sum(r.commands for r in rs),
        written=sum(r.written for r in rs),
        dropped=sum(r.dropped for r in rs),
        lost=sum(r.lost for r in rs),
    )


if __name__ == "__main__":
    sys.exit(main_quiet("bench.events_cost", __doc__ or "", run))
