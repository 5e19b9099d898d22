"""`machine run`: assemble the daemon, run the scan loop, and always leave the outputs safe."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

from hal.base import Hal, HalConfigError, HalError
from schema.events import DaemonStartEvent, DaemonStopEvent, WatchdogEvent
from schema.findings import Finding, Severity
from service import bus as zbus
from service.bus.exposure import warn_if_exposed
from service.config import HalBackend, MachineConfig
from service.eventlog import EVENTS_FILE, EventLog
from service.fastdata import FastDataServer, user_registers
from service.load import check_candidate
from service.machine import Machine
from service.params import ParamRegistry
from service.persist import BackgroundWriter, CalibrationStore, ParamStore
from service.runner import (
    SUPERVISOR_PID_ENV,
    LoopFailed,
    RealtimeRunner,
    die_with_parent,
    tune_thread,
)
from service.simwing import sim_hal, sim_port
from service.timing import CycleStats
from service.validate import finding_line
from service.watchdog import GuardedHal, Watchdog

log = logging.getLogger("machine")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_CONFIG = 2


@dataclass
class DaemonOptions:
    """How to reach the bus; the rest is in the machine config."""

    zenoh_config: Path | None = None
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)


def make_hal(config: MachineConfig, clock: object) -> Hal:
    """The configured backend; the simulator by default."""
    if config.hal.backend is HalBackend.REVPI:
        from hal.revpi import RevPiHal

        rp = config.hal.revpi
        return RevPiHal(config.hal.iomap, rp.procimg, rp.configrsc)
    return sim_hal(config)


def open_hal(config: MachineConfig, clock: object, source: str = "machine") -> Hal | None:
    """The backend, or None after printing why it cannot open as findings on stderr."""
    try:
        return make_hal(config, clock)
    except HalConfigError as exc:
        found = exc.findings
    except (HalError, OSError) as exc:  # anything else the backend meets while it opens
        found = [
            Finding(
                category="hal",
                severity=Severity.ERROR,
                path="/hal/backend",
                message=f"the {config.hal.backend} backend cannot open: {exc}",
            )
        ]
    for f in found:
        print(finding_line(source, f), file=sys.stderr)
    log.error("event=hal_failed backend=%s findings=%d", config.hal.backend, len(found))
    return None


def run_daemon(config: MachineConfig, options: DaemonOptions) -> int:
    """Run until SIGTERM/SIGINT; returns the process exit code."""
    supervisor = os.environ.get(SUPERVISOR_PID_ENV)
    if supervisor and not die_with_parent(int(supervisor)):
        # Never run unsupervised by accident: the supervisor is what makes outputs safe
        # when this process dies.
        log.error("event=supervisor_gone pid=%s", supervisor)
        return EXIT_FAILED
    clock = time.monotonic
    wall_offset = time.time() - clock()
    raw_hal = open_hal(config, clock)
    if raw_hal is None:
        return EXIT_CONFIG
    raw_hal.force_all_outputs_safe()
    hal = GuardedHal(raw_hal)
    writer = BackgroundWriter()
    store = CalibrationStore(Path(config.data_dir), writer)
    registry = ParamRegistry(config, ParamStore(Path(config.data_dir)), store.health)
    for warning in registry.warnings:
        log.warning("event=params_load detail=%r", warning)
    config = registry.config  # persisted online values survive a restart
    stats = CycleStats(config.loop.period_s, config.loop.stats_window, time.time())
    events = _event_log(config)
    machine = Machine(
        registry.live,
        hal,
        now=clock(),
        wall_offset=wall_offset,
        store=store,
        events=events,
        guard=hal,
        warnings=registry.warnings,
    )
    loop = machine.loop
    runner = RealtimeRunner(loop, config.loop.period_s, stats, spin_s=config.loop.spin_s)

    exit_deadline = threading.Timer(SHUTDOWN_DEADLINE_S, _exit_now, args=(raw_hal,))
    exit_deadline.daemon = True
    reason = ["runner stopped"]

    def on_signal(signum: int, frame: FrameType | None) -> None:
        log.info("event=signal signal=%s", signal.Signals(signum).name)
        reason[0] = f"signal {signal.Signals(signum).name}"
        runner.stop()
        with contextlib.suppress(RuntimeError):  # armed by an earlier signal already
            exit_deadline.start()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        zconf = zbus.zenoh_config(options.zenoh_config, options.listen, options.connect)
        warn_if_exposed(zconf, log)
        session = zbus.open_session(zconf)
    except Exception as exc:  # noqa: BLE001 - zenoh raises plain ZError; outputs already safe
        log.error("event=zenoh_open_failed error=%r", str(exc))
        hal.close()
        writer.close()
        _close_event_log(events, f"zenoh session could not open: {exc}", EXIT_FAILED)
        return EXIT_FAILED
    others = zbus.holders_of(session, config.key_base)
    if others:
        # One machine per id: a second daemon would take the first one's commands too.
        log.error(
            "event=duplicate_id id=%s other_session=%s action=refuse_start detail=%r",
            config.machine.id,
            ",".join(others),
            f"machine id {config.machine.id} is already alive on the network (session"
            f" {', '.join(others)}); stop that daemon or give this one another --id",
        )
        zbus.close_session(session)
        hal.close()
        writer.close()
        _close_event_log(events, "machine id already alive on the network", EXIT_FAILED)
        return EXIT_FAILED
    bus = zbus.ZenohBus(
        session,
        loop,
        stats,
        config,
        sim=sim_port(raw_hal),
        sim_elsewhere=bool(supervisor),
        params=registry,
        check_config=lambda candidate: check_candidate(registry.config, candidate),
        events=events,
    )
    loop.sink = bus

    def on_trip(stalled_s: float) -> None:
        bus.publish_watchdog_trip(stalled_s)
        if events is not None:
            events.emit_now(WatchdogEvent(stalled_s=stalled_s))

    watchdog = Watchdog(
        lambda: runner.heartbeat,
        hal,
        config.loop.period_s,
        config.loop.watchdog_periods,
        config.loop.watchdog_min_s,
        on_trip=on_trip,
        beat_at=lambda: runner.beat_at,
    )
    fastdata: FastDataServer | None = None
    code = EXIT_OK
    try:
        bus.start()
        watchdog.start()
        if config.fastdata.enabled:
            fastdata = FastDataServer(
                lambda: loop.published.axes,
                config.fastdata.host,
                config.fastdata.port,
                cycle=lambda: loop.cycle,
                registers=lambda: user_registers(registry.config),
            )
            fastdata.start()
            log.info("event=fastdata_started address=%s:%d", *fastdata.address)
        applied = tune_thread(config.loop.gc_freeze, config.loop.cpu, config.loop.rt_priority)
        log.info(
            "event=started id=%s hal=%s period_s=%g tuning=%s",
            config.machine.id,
            config.hal.backend,
            config.loop.period_s,
            ",".join(applied) or "none",
        )
        runner.run()
    except LoopFailed as exc:
        log.error("event=loop_failed error=%r", str(exc))
        code = EXIT_FAILED
        reason[0] = f"loop failed: {exc}"
    finally:
        # Outputs first: nothing below may delay them.
        loop.go_safe()
        watchdog.stop()
        if fastdata is not None:
            fastdata.close()
        loop.reject_pending("machine daemon is shutting down")
        loop.abort_motion(clock(), "machine daemon is shutting down")
        if events is not None:
            # Written and published while the bus is still up.
            events.emit_now(DaemonStopEvent(reason=reason[0], exit_code=code))
            events.flush(timeout=1.0)
        bus.close()
        closed = zbus.close_session(session)
        if not closed:
            # An open session can hang the interpreter's exit: keep the deadline armed.
            log.warning("event=zenoh_close_timeout")
            with contextlib.suppress(RuntimeError):
                exit_deadline.start()
        hal.close()
        writer.flush()
        writer.close()
        if events is not None:
            events.close()
        # One line that says the outputs were forced safe (step 1 above), for logs and tests.
        log.info("event=stopped code=%d outputs=safe cycles=%d", code, stats.cycles)
        if closed:
            exit_deadline.cancel()
    return code


def _event_log(config: MachineConfig) -> EventLog | None:
    """The event history, started, with this start recorded first; None when disabled."""
    if not config.events.enabled:
        return None
    events = EventLog(Path(config.data_dir) / EVENTS_FILE, config.machine.id, config.events)
    events.start()
    events.emit_now(
        DaemonStartEvent(
            pid=os.getpid(),
            hal=str(config.hal.backend),
            period_s=config.loop.period_s,
            previous_stop_clean=events.previous_stop_clean,
        )
    )
    return events


def _close_event_log(events: EventLog | None, reason: str, code: int) -> None:
    if events is not None:
        events.emit_now(DaemonStopEvent(reason=reason, exit_code=code))
        events.close()


SHUTDOWN_DEADLINE_S = 5.0
"""A stop that has not finished by then (a blocked call in the bus, a hung session close) ends
the process anyway, outputs forced safe first: `docker compose stop` gives 10 s."""


def _exit_now(hal: Hal) -> None:
    try:
        hal.force_all_outputs_safe()
    finally:
        log.error("event=shutdown_stuck deadline_s=%g action=exit", SHUTDOWN_DEADLINE_S)
        logging.shutdown()
        os._exit(EXIT_FAILED)
