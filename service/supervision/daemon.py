"""`machine run`: assemble the daemon, run the scan loop, and always leave the outputs safe."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from hal.backends import backend
from hal.base import Hal, HalConfigError, HalError
from schema.events import DaemonStartEvent, DaemonStopEvent, WatchdogEvent
from service import bus as zbus
from service.adapters.eventlog import EVENTS_FILE, EventLog
from service.adapters.fastdata import FastDataServer, user_registers
from service.adapters.heartbeat import HeartbeatFile
from service.adapters.history import HistoryProcess
from service.adapters.replay import Recalled, recall
from service.bus.exposure import warn_if_exposed
from service.config.load import check_candidate
from service.config.model import MachineConfig
from service.config.validate import Category, finding_line, one_error
from service.core.beat import BeatWriter, beat_from_env
from service.core.machine import Machine
from service.core.params import ParamRegistry
from service.core.persist import BackgroundWriter, CalibrationStore, ParamStore
from service.core.port import LoopPort
from service.core.runner import LoopFailed, RealtimeRunner
from service.core.safety import in_effect
from service.core.statemachine.deadman import Heartbeats
from service.core.timing import CycleStats
from service.core.tuning import (
    SUPERVISOR_PID_ENV,
    die_with_parent,
    gc_threshold,
    pin_process,
    slice_process,
    switch_interval,
    tune_thread,
)
from service.core.watchdog import GuardedHal, Watchdog
from service.logfmt import flush_logs
from service.signals import SignalThread
from service.supervision.malloc import bound_malloc_arenas
from service.supervision.simport import sim_port
from service.threads import name_callback_threads

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
    """The configured backend, found by name (`hal.backends`); the simulator by default. On
    the real clock: an injected scan stall really sleeps."""
    hal = config.hal
    return backend(hal.backend).open(hal.iomap, hal.settings(), time.monotonic, time.sleep)


def open_hal(config: MachineConfig, clock: object, source: str = "machine") -> Hal | None:
    """The backend, or None after printing why it cannot open as findings on stderr."""
    try:
        return make_hal(config, clock)
    except HalConfigError as exc:
        found = exc.findings
    except (HalError, OSError) as exc:  # anything else the backend meets while it opens
        message = f"the {config.hal.backend} backend cannot open: {exc}"
        found = one_error(Category.HAL, message, "/hal/backend").findings
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
    daemon = Daemon(config, options, supervised=bool(supervisor))
    # Before Zenoh's threads start: each takes an arena, and inherits the affinity.
    if bound_malloc_arenas(config.loop.malloc_arenas):
        daemon.tuned.append(f"malloc_arenas={config.loop.malloc_arenas}")
    if config.loop.cpus is not None and (pinned := pin_process(config.loop.cpus)):
        daemon.tuned.append(pinned)
    if config.loop.slice_ns is not None and (sliced := slice_process(config.loop.slice_ns)):
        daemon.tuned.append(sliced)
    if runtime := zbus.use_runtime(config.bus.zenoh_threads):
        daemon.tuned.append(runtime)
    # The process ends when `run` returns: a signal from then on must not kill it (the
    # default action) before its last log lines are written.
    daemon.signals_after = signal.SIG_IGN
    return daemon.run()


class StartRefused(Exception):
    """A setup step found the daemon cannot run; what was set up so far is undone."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


class Daemon:
    """`machine run` assembled step by step on one `ExitStack`: each step registers its own
    undo, so teardown runs in reverse setup order, and the last step pushes "outputs safe",
    which therefore runs first on any way out."""

    def __init__(
        self, config: MachineConfig, options: DaemonOptions, *, supervised: bool = False
    ) -> None:
        self.config = config
        self.options = options
        self.supervised = supervised
        """A supervisor answers `sim/**` for this machine (it runs the simulated world)."""
        self.clock = time.monotonic
        self.code = EXIT_OK
        self.reason = "runner stopped"
        self.served = False
        self.session_closed = True
        self.events: EventLog | None = None
        self.runner: RealtimeRunner | None = None
        self.exit_deadline: threading.Timer | None = None
        self._stop_asked = False
        self.signals: SignalThread | None = None
        self.signals_repeated = 0
        self.signals_after: signal.Handlers | None = None
        """What SIGTERM and SIGINT get once `run` returns; None: the handlers from before."""
        self._stop_recorded = False
        self.beat: BeatWriter | None = beat_from_env() if supervised else None
        """The shared record the supervisor's output guard watches (`service.core.beat`)."""
        self.tuned: list[str] = []
        """What `run_daemon` applied to the process before it started (`loop.malloc_arenas`,
        `loop.cpus`, `loop.slice_s`, `bus.zenoh_threads`), for the start line's tuning."""

    def run(self) -> int:
        """Set up, serve until stopped, undo; the exit code (the `EXIT_*` constants)."""
        try:
            with contextlib.ExitStack() as stack:
                try:
                    self._assemble(stack)
                except StartRefused as exc:
                    self.code, self.reason = exc.code, exc.reason
                    return exc.code
                except Exception as exc:  # recorded as the stop's reason, then raised on
                    self.code, self.reason = EXIT_FAILED, f"start failed: {exc}"
                    raise
                self._serve()
        finally:
            if self.served:
                # One line that says the outputs were forced safe (the first undo), for logs
                # and tests.
                repeated = self.signals_repeated
                log.info(
                    "event=stopped code=%d outputs=safe cycles=%d%s",
                    self.code,
                    self.stats.cycles,
                    f" signals_repeated={repeated}" if repeated else "",
                )
            if self.session_closed and self.exit_deadline is not None:
                self.exit_deadline.cancel()
            if self.signals is not None:
                self.signals.close(then=self.signals_after)
        return self.code

    # ------------------------------------------------------------------------------ setup
    def _assemble(self, stack: contextlib.ExitStack) -> None:
        """The setup steps in order; each registers its undo as soon as it has succeeded."""
        hal = self._open_hal(stack)
        store, registry = self._open_storage(stack)
        recalled = self._recall()  # before this run's history writer takes the file
        self._open_event_log(stack)
        # Handled on a thread of their own, never inside the code a signal interrupts; until
        # `run` returns, so a signal during the teardown is handled too.
        self.signals = SignalThread(self._on_signal)
        self.signals.start()
        session = self._open_session(stack)
        self._refuse_duplicate(session)
        self._build_machine(hal, store, registry, session)
        self._remember(recalled)
        _on_exit(stack, "bus", self.bus.close)
        self.bus.start()
        name_callback_threads()  # zenoh-python's callback threads, for `top -H`
        _on_exit(stack, "wind_down", self._wind_down)  # while the bus is up: last answers
        self._start_watchdog(stack, hal)
        if (beat := HeartbeatFile.from_env(self.port.cycle)) is not None:  # healthcheck
            _on_exit(stack, "heartbeat_file", beat.stop)
            beat.start()
        if self.config.fastdata.enabled:
            self._start_fastdata(stack, registry)
        _on_exit(stack, "outputs_safe", self.loop.go_safe)  # pushed last, so undone first

    def _open_hal(self, stack: contextlib.ExitStack) -> GuardedHal:
        """The backend, outputs safe, behind the watchdog's latch; armed exit deadline."""
        raw_hal = open_hal(self.config, self.clock)
        if raw_hal is None:
            raise StartRefused(EXIT_CONFIG, "the HAL could not open")
        raw_hal.force_all_outputs_safe()
        self.raw_hal = raw_hal
        self.exit_deadline = threading.Timer(SHUTDOWN_DEADLINE_S, _exit_now, args=(raw_hal,))
        self.exit_deadline.daemon = True
        hal = GuardedHal(raw_hal, self.beat)
        _on_exit(stack, "hal", hal.close)
        return hal

    def _open_storage(self, stack: contextlib.ExitStack) -> tuple[CalibrationStore, ParamRegistry]:
        """Calibration and online parameters in the data dir; persisted values apply now."""
        data_dir = Path(self.config.data_dir)
        writer = BackgroundWriter()
        _on_exit(stack, "storage", _flush_and_close, writer)
        store = CalibrationStore(data_dir, writer)
        _on_exit(stack, "calibration", store.close)  # before the writer's own close
        registry = ParamRegistry(self.config, ParamStore(data_dir), store.health)
        self.config = config = registry.config  # persisted online values survive a restart
        self.stats = CycleStats(
            config.loop.period_s,
            config.loop.stats_window,
            time.time(),
            limit_s=config.loop.watchdog_limit_s,
        )
        return store, registry

    def _recall(self) -> Recalled:
        """The answers of the commands before this start (service/adapters/replay.py)."""
        config = self.config
        if not config.events.enabled:
            return Recalled()
        path = Path(config.data_dir) / EVENTS_FILE
        return recall(path, config.machine.id, config.bus.transaction_window)

    def _remember(self, recalled: Recalled) -> None:
        """A repeat of a transaction answered before this start gets that answer again."""
        self.loop.remember(recalled.replies, recalled.completions)
        log.info(
            "event=transactions_recalled commands=%d completions=%d since=%s",
            len(recalled.replies),
            len(recalled.completions),
            "-" if recalled.since is None else f"{recalled.since:.3f}",
        )

    def _open_event_log(self, stack: contextlib.ExitStack) -> None:
        self.events = _event_log(self.config)
        _on_exit(stack, "event_log", self._close_events)

    def _open_session(self, stack: contextlib.ExitStack) -> zbus.Session:
        options = self.options
        try:
            zconf = zbus.zenoh_config(options.zenoh_config, options.listen, options.connect)
            warn_if_exposed(zconf, log)
            session = zbus.open_session(zconf)
        except Exception as exc:  # zenoh raises plain ZError; the outputs are safe already
            log.error("event=zenoh_open_failed error=%r", str(exc))
            raise StartRefused(EXIT_FAILED, f"zenoh session could not open: {exc}") from exc
        _on_exit(stack, "session", self._close_session, session)
        return session

    def _refuse_duplicate(self, session: zbus.Session) -> None:
        """One machine per id: a second daemon would take the first one's commands too."""
        config = self.config
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

    def _build_machine(
        self,
        hal: GuardedHal,
        store: CalibrationStore,
        registry: ParamRegistry,
        session: zbus.Session,
    ) -> None:
        """The machine, its runner, and the bus, each given what it uses: the loop publishes
        through the bus's publications (made first), the bus reaches the loop through its port
        (made after it)."""
        config, clock = self.config, self.clock
        publications = zbus.Publications(session, self.stats, config, time.time, self.events)
        machine = Machine(
            registry.live,
            hal,
            now=clock(),
            wall_offset=time.time() - clock(),
            store=store,
            events=self.events,
            guard=hal,
            warnings=registry.warnings,
            sink=publications,
            beats=Heartbeats(),
            clock=clock,
        )
        self.loop = machine.loop
        self.port = LoopPort(machine.loop, clock)
        self.bus = zbus.ZenohBus(
            self.port,
            publications,
            io_keys=[f"io/{p.kind}/{p.name}" for p in machine.points.all()],
            sim=sim_port(backend(self.config.hal.backend).simulator(self.raw_hal)),
            sim_elsewhere=self.supervised,
            params=registry,
            check_config=lambda candidate: check_candidate(registry.config, candidate),
        )
        self.runner = RealtimeRunner(
            self.loop,
            config.loop.period_s,
            self.stats,
            spin_s=config.loop.spin_s,
            stall_limit_s=config.loop.watchdog_limit_s,
            beat=self.beat,
            wall=time.time,  # the host's clock can be set while the daemon runs (NTP)
        )
        if self.beat is not None:
            self.beat.start(config.loop.watchdog_limit_s)
        if self._stop_asked:  # a signal during setup: serve no cycle
            self.runner.stop()

    def _start_watchdog(self, stack: contextlib.ExitStack, hal: GuardedHal) -> None:
        loop, runner = self.config.loop, self.runner
        assert runner is not None
        watchdog = Watchdog(
            lambda: runner.heartbeat,
            hal,
            loop.period_s,
            loop.watchdog_periods,
            loop.watchdog_min_s,
            on_trip=self._on_watchdog_trip,
            beat_at=lambda: runner.beat_at,
            finished=lambda: runner.finished,
        )
        runner.on_stall = watchdog.after_stall
        _on_exit(stack, "watchdog", watchdog.stop)
        watchdog.start()

    def _start_fastdata(self, stack: contextlib.ExitStack, registry: ParamRegistry) -> None:
        fd, port = self.config.fastdata, self.port
        server = FastDataServer(
            lambda: port.snapshot().axes,
            fd.host,
            fd.port,
            cycle=port.cycle,
            registers=lambda: user_registers(registry.config),
        )
        _on_exit(stack, "fastdata", server.close)
        server.start()
        log.info("event=fastdata_started address=%s:%d", *server.address)

    # ------------------------------------------------------------------------------ serve
    def _serve(self) -> None:
        config = self.config
        self.served = True
        loop = config.loop
        applied = tune_thread(loop.gc_freeze, loop.cpu, loop.rt_priority)
        applied.append(gc_threshold(loop.gc_threshold))
        applied.append(switch_interval(loop.switch_interval_s))
        applied += self.tuned
        log.info(
            "event=started id=%s hal=%s period_s=%g tuning=%s",
            config.machine.id,
            config.hal.backend,
            config.loop.period_s,
            ",".join(applied) or "none",
        )
        assert self.runner is not None
        try:
            self.runner.run()
        except LoopFailed as exc:
            log.error("event=loop_failed error=%r", str(exc))
            self.code = EXIT_FAILED
            self.reason = f"loop failed: {exc}"

    def _on_signal(self, signum: int) -> None:
        """SIGTERM or SIGINT, on the signal thread (`SignalThread`): the first one stops the
        daemon; one more while it stops is only counted (`event=stopped ... signals_repeated`)."""
        name = signal.Signals(signum).name
        if self._stop_asked:
            self.signals_repeated += 1
            return
        log.info("event=signal signal=%s", name)
        self.reason = f"signal {name}"
        self._stop_asked = True
        if self.runner is not None:
            self.runner.stop()
        self._arm_exit_deadline()

    def _on_watchdog_trip(self, stalled_s: float) -> None:
        self.bus.publish_watchdog_trip(stalled_s)
        if self.events is not None:
            self.events.emit_now(WatchdogEvent(stalled_s=stalled_s))

    # --------------------------------------------------------------------------- teardown
    def _wind_down(self) -> None:
        """The runner has stopped: every queued command and the motion under way get their
        answer, and the stop is recorded, while the bus can still carry them."""
        now = self.clock()
        self.loop.reject_pending("machine daemon is shutting down")
        self.loop.abort_motion(now, "machine daemon is shutting down")
        if self.events is not None:
            self._record_stop(self.events)
            self.events.flush(timeout=1.0)

    def _record_stop(self, events: EventLog) -> None:
        if not self._stop_recorded:
            self._stop_recorded = True
            events.emit_now(DaemonStopEvent(reason=self.reason, exit_code=self.code))

    def _close_events(self) -> None:
        if self.events is not None:
            self._record_stop(self.events)
            self.events.close()

    def _close_session(self, session: zbus.Session) -> None:
        self.session_closed = zbus.close_session(session)
        if not self.session_closed:
            # An open session can hang the interpreter's exit: keep the deadline armed.
            log.warning("event=zenoh_close_timeout")
            self._arm_exit_deadline()

    def _arm_exit_deadline(self) -> None:
        if self.exit_deadline is not None:
            with contextlib.suppress(RuntimeError):  # armed already
                self.exit_deadline.start()


def _on_exit(
    stack: contextlib.ExitStack, step: str, undo: Callable[..., object], *args: object
) -> None:
    """Register the undo of a setup step; a debug line names each one as it runs, so a
    shutdown that hangs shows where."""

    def run() -> None:
        log.debug("event=undo step=%s", step)
        undo(*args)

    stack.callback(run)


def _flush_and_close(writer: BackgroundWriter) -> None:
    writer.flush()
    writer.close()


def _event_log(config: MachineConfig) -> EventLog | None:
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


SHUTDOWN_DEADLINE_S = 5.0
"""A stop that has not finished by then (a blocked call in the bus, a hung session close) ends
the process anyway, outputs forced safe first: `docker compose stop` gives 10 s."""


def _exit_now(hal: Hal) -> None:
    try:
        hal.force_all_outputs_safe()
    finally:
        log.error("event=shutdown_stuck deadline_s=%g action=exit", SHUTDOWN_DEADLINE_S)
        flush_logs()
        os._exit(EXIT_FAILED)
