"""`machine run`: the daemon's lifecycle. Set up on one `ExitStack` (the parts are made in
service/supervision/assembly.py), serve until a signal or a failure, wind down while the bus can
still carry the last answers, and always leave the outputs safe."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time

from ride_machine.hal.base import Hal
from ride_machine.schema.events import DaemonStopEvent, WatchdogEvent
from ride_machine.service import bus as zbus
from ride_machine.service.adapters.eventlog import EventLog
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.beat import BeatWriter, beat_from_env
from ride_machine.service.core.scan.runner import LoopFailed, RealtimeRunner
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.scan.tuning import (
    SUPERVISOR_PID_ENV,
    die_with_parent,
    gc_threshold,
    pin_process,
    slice_process,
    switch_interval,
    tune_thread,
)
from ride_machine.service.logfmt import flush_logs
from ride_machine.service.signals import SignalThread
from ride_machine.service.threads import name_callback_threads

from .assembly import (
    Built,
    DaemonOptions,
    Wiring,
    build_machine,
    event_log,
    guarded_hal,
    on_exit,
    open_session,
    open_storage,
    recall_answers,
    refuse_duplicate,
    remember,
    start_fastdata,
    start_heartbeat_file,
    start_watchdog,
)
from .malloc import bound_malloc_arenas
from .outcome import EXIT_FAILED, EXIT_OK, StartRefused

log = logging.getLogger("machine")


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
        """The shared record the supervisor's output guard watches (`service.core.scan.beat`)."""
        self.raw_hal: Hal
        self.stats: CycleStats
        self.built: Built
        """The running machine (service/supervision/assembly.py), once assembled."""
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
        """The setup steps in order (service/supervision/assembly.py); each registers its undo
        as soon as it has succeeded."""
        config = self.config
        raw_hal, hal = guarded_hal(stack, config, self.beat)
        self.raw_hal = raw_hal  # the backend itself: what tests read the outputs of
        self.exit_deadline = threading.Timer(SHUTDOWN_DEADLINE_S, _exit_now, args=(raw_hal,))
        self.exit_deadline.daemon = True
        storage = open_storage(stack, config)
        self.config = config = storage.registry.config  # persisted online values apply now
        self.stats = storage.stats
        recalled = recall_answers(config)  # before this run's history writer takes the file
        self.events = event_log(config)
        on_exit(stack, "event_log", self._close_events)
        # Handled on a thread of their own, never inside the code a signal interrupts; until
        # `run` returns, so a signal during the teardown is handled too.
        self.signals = SignalThread(self._on_signal)
        self.signals.start()
        session = open_session(self.options)
        on_exit(stack, "session", self._close_session, session)
        refuse_duplicate(session, config)
        wiring = Wiring(
            raw_hal,
            hal,
            storage,
            session,
            self.events,
            self.beat,
            self.supervised,
            self._on_watchdog_trip,
        )
        self.built = built = build_machine(config, wiring)
        self.runner = built.runner
        if self._stop_asked:  # a signal during setup: serve no cycle
            built.runner.stop()
        remember(built.loop, recalled)
        on_exit(stack, "bus", built.bus.close)
        built.bus.start()
        name_callback_threads()  # zenoh-python's callback threads, for `top -H`
        on_exit(stack, "wind_down", self._wind_down)  # while the bus is up: last answers
        start_watchdog(stack, built.watchdog)
        start_heartbeat_file(stack, built.port)  # the container's healthcheck
        if config.fastdata.enabled:
            start_fastdata(stack, config, built.port, storage.registry)
        on_exit(stack, "outputs_safe", built.loop.go_safe)  # pushed last, so undone first

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
        self.built.bus.publish_watchdog_trip(stalled_s)
        if self.events is not None:
            self.events.emit_now(WatchdogEvent(stalled_s=stalled_s))

    # --------------------------------------------------------------------------- teardown
    def _wind_down(self) -> None:
        """The runner has stopped: every queued command and the motion under way get their
        answer, and the stop is recorded, while the bus can still carry them."""
        now = self.clock()
        loop = self.built.loop
        loop.reject_pending("machine daemon is shutting down")
        loop.abort_motion(now, "machine daemon is shutting down")
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
