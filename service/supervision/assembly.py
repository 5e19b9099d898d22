"""The daemon's parts, made and wired: the HAL behind the watchdog's latch, the storage, the event
history, the Zenoh session, the machine with its runner and bus, the watchdog, the heartbeat
file and fastdata. Each step that leaves something to undo registers the undo on the daemon's
`ExitStack` (`on_exit`); the order of the steps and what the daemon does with the parts (serve,
stop, wind down) are service/supervision/daemon.py's."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ride_machine.hal.backends import backend
from ride_machine.hal.base import Hal, HalConfigError, HalError
from ride_machine.schema.events import DaemonStartEvent
from ride_machine.service import bus as zbus
from ride_machine.service.adapters.eventlog import EVENTS_FILE, EventLog
from ride_machine.service.adapters.fastdata import FastDataServer, user_registers
from ride_machine.service.adapters.heartbeat import HeartbeatFile
from ride_machine.service.adapters.history import HistoryProcess
from ride_machine.service.adapters.replay import Recalled, recall
from ride_machine.service.bus.exposure import warn_if_exposed
from ride_machine.service.config.load import check_candidate
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.config.validate import Category, finding_line, one_error
from ride_machine.service.core.scan.beat import BeatWriter
from ride_machine.service.core.scan.loop import ScanLoop
from ride_machine.service.core.scan.machine import Machine
from ride_machine.service.core.scan.port import LoopPort
from ride_machine.service.core.scan.runner import RealtimeRunner
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.scan.watchdog import GuardedHal, Watchdog
from ride_machine.service.core.statemachine.deadman import Heartbeats
from ride_machine.service.core.storage.params import ParamRegistry
from ride_machine.service.core.storage.persist import BackgroundWriter, CalibrationStore, ParamStore
from ride_machine.service.core.storage.safety import in_effect

from .outcome import EXIT_CONFIG, EXIT_FAILED, StartRefused
from .simport import sim_port

log = logging.getLogger("machine")


@dataclass
class DaemonOptions:
    """How to reach the bus; the rest is in the machine config."""

    zenoh_config: Path | None = None
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)


def make_hal(config: MachineConfig) -> Hal:
    """The configured backend, found by name (`hal.backends`); the simulator by default. On
    the real clock: an injected scan stall really sleeps."""
    hal = config.hal
    return backend(hal.backend).open(hal.iomap, hal.settings(), time.monotonic, time.sleep)


def open_hal(config: MachineConfig, source: str = "machine") -> Hal | None:
    """The backend, or None after printing why it cannot open as findings on stderr."""
    try:
        return make_hal(config)
    except HalConfigError as exc:
        found = exc.findings
    except (HalError, OSError) as exc:  # anything else the backend meets while it opens
        message = f"the {config.hal.backend} backend cannot open: {exc}"
        found = one_error(Category.HAL, message, "/hal/backend").findings
    for f in found:
        print(finding_line(source, f), file=sys.stderr)
    log.error("event=hal_failed backend=%s findings=%d", config.hal.backend, len(found))
    return None


def on_exit(
    stack: contextlib.ExitStack, step: str, undo: Callable[..., object], *args: object
) -> None:
    """Register the undo of a setup step; a debug line names each one as it runs, so a
    shutdown that hangs shows where."""

    def run() -> None:
        log.debug("event=undo step=%s", step)
        undo(*args)

    stack.callback(run)


def guarded_hal(
    stack: contextlib.ExitStack, config: MachineConfig, beat: BeatWriter | None
) -> tuple[Hal, GuardedHal]:
    """The backend with its outputs safe, and the same behind the watchdog's latch."""
    raw_hal = open_hal(config)
    if raw_hal is None:
        raise StartRefused(EXIT_CONFIG, "the HAL could not open")
    raw_hal.force_all_outputs_safe()
    hal = GuardedHal(raw_hal, beat)
    on_exit(stack, "hal", hal.close)
    return raw_hal, hal


@dataclass(frozen=True)
class Storage:
    """Calibration and online parameters in the data dir, and the cycle statistics of the
    config they leave in force."""

    store: CalibrationStore
    registry: ParamRegistry
    stats: CycleStats


def open_storage(stack: contextlib.ExitStack, config: MachineConfig) -> Storage:
    """Calibration and online parameters in the data dir; persisted values apply now
    (`registry.config`: persisted online values survive a restart)."""
    data_dir = Path(config.data_dir)
    writer = BackgroundWriter()
    on_exit(stack, "storage", _flush_and_close, writer)
    store = CalibrationStore(data_dir, writer)
    on_exit(stack, "calibration", store.close)  # before the writer's own close
    registry = ParamRegistry(config, ParamStore(data_dir), store.health)
    loop = registry.config.loop
    stats = CycleStats(loop.period_s, loop.stats_window, time.time(), limit_s=loop.watchdog_limit_s)
    return Storage(store, registry, stats)


def _flush_and_close(writer: BackgroundWriter) -> None:
    writer.flush()
    writer.close()


def recall_answers(config: MachineConfig) -> Recalled:
    """The answers of the commands before this start (service/adapters/replay.py); read
    before this run's history writer takes the file."""
    if not config.events.enabled:
        return Recalled()
    path = Path(config.data_dir) / EVENTS_FILE
    return recall(path, config.machine.id, config.bus.transaction_window)


def remember(loop: ScanLoop, recalled: Recalled) -> None:
    """A repeat of a transaction answered before this start gets that answer again."""
    loop.remember(recalled.replies, recalled.completions)
    log.info(
        "event=transactions_recalled commands=%d completions=%d since=%s",
        len(recalled.replies),
        len(recalled.completions),
        "-" if recalled.since is None else f"{recalled.since:.3f}",
    )


def event_log(config: MachineConfig) -> EventLog | None:
    """The event history, started, with this start recorded first; None when disabled."""
    if not config.events.enabled:
        return None
    kind = HistoryProcess if config.events.process else EventLog
    events = kind(Path(config.data_dir) / EVENTS_FILE, config.machine.id, config.events)
    events.start()
    events.emit_now(
        DaemonStartEvent(
            pid=os.getpid(),
            hal=str(config.hal.backend),
            period_s=config.loop.period_s,
            previous_stop_clean=events.previous_stop_clean,
            safety=in_effect(config),
        )
    )
    return events


def open_session(options: DaemonOptions) -> zbus.Session:
    """The daemon's Zenoh session; a start refused (1) when Zenoh cannot open it."""
    try:
        zconf = zbus.zenoh_config(options.zenoh_config, options.listen, options.connect)
        warn_if_exposed(zconf, log)
        return zbus.open_session(zconf)
    except Exception as exc:  # zenoh raises plain ZError; the outputs are safe already
        log.error("event=zenoh_open_failed error=%r", str(exc))
        raise StartRefused(EXIT_FAILED, f"zenoh session could not open: {exc}") from exc


def refuse_duplicate(session: zbus.Session, config: MachineConfig) -> None:
    """One machine per id: a second daemon would take the first one's commands too."""
    others = zbus.holders_of(session, config.key_base)
    if not others:
        return
    log.error(
        "event=duplicate_id id=%s other_session=%s action=refuse_start detail=%r",
        config.machine.id,
        ",".join(others),
        f"machine id {config.machine.id} is already alive on the network (session"
        f" {', '.join(others)}); stop that daemon or give this one another --id",
    )
    raise StartRefused(EXIT_FAILED, "machine id already alive on the network")


@dataclass(frozen=True)
class Built:
    """The running machine: its scan loop, the port the bus reaches it by, the bus, and the
    runner that cycles it."""

    loop: ScanLoop
    port: LoopPort
    bus: zbus.ZenohBus
    runner: RealtimeRunner
    watchdog: Watchdog
    """Given to the runner as it was made; started once the bus is up."""


@dataclass(frozen=True)
class Wiring:
    """What the machine is built from, besides its config."""

    raw_hal: Hal
    hal: GuardedHal
    storage: Storage
    session: zbus.Session
    events: EventLog | None
    beat: BeatWriter | None
    supervised: bool
    """A supervisor answers `sim/**` for this machine (it runs the simulated world)."""
    on_trip: Callable[[float], None]
    """What the watchdog does when it trips, besides forcing the outputs safe."""


def build_machine(config: MachineConfig, w: Wiring) -> Built:
    """The machine, its runner, and the bus, each given what it uses: the loop publishes
    through the bus's publications (made first), the bus reaches the loop through its port
    (made after it)."""
    clock = time.monotonic
    stats, registry = w.storage.stats, w.storage.registry
    publications = zbus.Publications(w.session, stats, config, time.time, w.events)
    machine = Machine(
        registry.live,
        w.hal,
        now=clock(),
        wall_offset=time.time() - clock(),
        store=w.storage.store,
        events=w.events,
        guard=w.hal,
        warnings=registry.warnings,
        sink=publications,
        beats=Heartbeats(),
        clock=clock,
    )
    port = LoopPort(machine.loop, clock)
    bus = zbus.ZenohBus(
        port,
        publications,
        io_keys=[f"io/{p.kind}/{p.name}" for p in machine.points.all()],
        sim=sim_port(backend(config.hal.backend).simulator(w.raw_hal)),
        sim_elsewhere=w.supervised,
        params=registry,
        check_config=lambda candidate: check_candidate(registry.config, candidate),
    )
    limit = config.loop.watchdog_limit_s
    watchdog = Watchdog(w.hal, limit, on_trip=w.on_trip)
    runner = RealtimeRunner(
        machine.loop,
        config.loop.period_s,
        stats,
        spin_s=config.loop.spin_s,
        watchdog=watchdog,
        beat=w.beat,
        wall=time.time,  # the host's clock can be set while the daemon runs (NTP)
    )
    if w.beat is not None:
        w.beat.start(limit)
    return Built(machine.loop, port, bus, runner, watchdog)


def start_watchdog(stack: contextlib.ExitStack, watchdog: Watchdog) -> None:
    on_exit(stack, "watchdog", watchdog.stop)
    watchdog.start()


def start_heartbeat_file(stack: contextlib.ExitStack, port: LoopPort) -> None:
    """The file a container's healthcheck reads, where the environment asks for one."""
    if (beat := HeartbeatFile.from_env(port.cycle)) is not None:
        on_exit(stack, "heartbeat_file", beat.stop)
        beat.start()


def start_fastdata(
    stack: contextlib.ExitStack, config: MachineConfig, port: LoopPort, registry: ParamRegistry
) -> None:
    fd = config.fastdata
    server = FastDataServer(
        lambda: port.published().axes,
        fd.host,
        fd.port,
        cycle=port.cycle,
        registers=lambda: user_registers(registry.config),
    )
    on_exit(stack, "fastdata", server.close)
    server.start()
    log.info("event=fastdata_started address=%s:%d", *server.address)
