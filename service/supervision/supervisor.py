"""`machine supervise`: run the daemon as a child process that may die but never leaves outputs on.

If the child dies (a crash, SIGKILL, an exit nobody asked for) or freezes (its liveliness token
goes while the process still exists), the supervisor writes the safe output image itself,
publishes FAULT_HW (DAEMON_DIED) for the machine, and restarts the daemon with back-off; the new
daemon comes up with outputs safe and not home. The supervisor is the machine's Zenoh router
(see `service.bus.supervisor`), so Riders keep their session across restarts.

With the simulator the ride's world runs in a plant process of its own (`sim.plant`) behind a
process-image file and the child runs the RevPi backend on that file, so the world outlives the
daemon, keeps its clock while the supervisor and the daemon are frozen together, and tests can
watch it; on a Revolution Pi the supervisor writes the safe image to the real process image.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from common.credentials import MACHINE, CredentialError, env_name
from hal.backends import World
from hal.base import HalConfigError, HalError
from service import bus as zbus
from service.bus.exposure import warn_if_exposed
from service.bus.supervisor import (
    SupervisorBus,
    child_config,
    requires_credentials,
    router_config,
)
from service.config.model import MachineConfig
from service.config.validate import finding_line
from service.core.beat import BEAT_FD_ENV, BeatReader, create_beat_fd
from service.core.tuning import SUPERVISOR_PID_ENV
from service.signals import SignalThread
from service.supervision.daemon import DaemonOptions, StartRefused
from service.supervision.field import SafeOutputs, open_field
from service.supervision.malloc import bound_malloc_arenas
from service.supervision.outputguard import OutputGuard, Stall
from service.supervision.procstate import describe, threads
from service.supervision.restarts import Backoff, Child, Event, Kind, describe_exit
from service.supervision.simport import sim_port
from service.supervision.toml_out import to_toml, write_private
from service.threads import NamedThread

log = logging.getLogger("machine.supervisor")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_CONFIG = 2
SUPERVISOR_DIR = "supervisor"
HANG_S = 1.0
"""The default hang limit: what the shipped Zenoh profiles' lease gave before (1 s)."""


@dataclass(frozen=True)
class SupervisorOptions:
    """Restart policy and bounds."""

    backoff_s: float = 0.5
    backoff_max_s: float = 8.0
    stable_s: float = 10.0
    """A child up this long resets the back-off to `backoff_s`."""
    start_timeout_s: float = 30.0
    """A child whose liveliness token has not appeared by then is killed and restarted."""
    exit_grace_s: float = 1.0
    """After the token goes: how long a child that is still running may take to exit."""
    stop_timeout_s: float = 10.0
    hang_s: float | None = None
    """A daemon whose scan has completed no cycle for this long is killed and restarted,
    whatever its outputs (they were made safe at the watchdog limit if any was on); None:
    `HANG_S`, or three watchdog limits when that is longer."""
    world_period_s: float = 0.005
    log_level: str = "info"
    plant_dir: Path | None = None
    """With the simulator: attach to a plant already running there (`--plant`, a compose
    service of its own) instead of starting one as a child."""


class Supervisor:
    """Owns the child daemon, the safe-output path, the router session and (sim) the world."""

    def __init__(
        self, config: MachineConfig, zenoh: DaemonOptions, options: SupervisorOptions
    ) -> None:
        self.config = config
        self.zenoh = zenoh
        self.options = options
        self.dir = Path(config.data_dir).resolve() / SUPERVISOR_DIR
        self.events: queue.SimpleQueue[Event] = queue.SimpleQueue()  # put() is signal-safe
        self._stop_asked = False
        self.signals_repeated = 0
        self.signals_after: signal.Handlers | None = None
        """What SIGTERM and SIGINT get once `run` returns; None: the handlers from before."""
        self.child: Child | None = None
        self.generation = 0
        self.world: World | None = None
        self.safe: SafeOutputs | None = None
        self.backoff = Backoff(options.backoff_s, options.backoff_max_s)
        self.bus: SupervisorBus
        self.beat_fd = create_beat_fd()
        self.beat = BeatReader(self.beat_fd)
        """The record the daemon child stamps every cycle (`service.core.beat`)."""
        self.guard: OutputGuard | None = None
        self._sockdir = Path(tempfile.mkdtemp(prefix="machine-sup-"))
        self.private = f"unixsock-stream/{self._sockdir / 'zenoh.sock'}"

    # ------------------------------------------------------------------------- lifecycle
    def run(self) -> int:
        """Until SIGTERM/SIGINT (0), a config problem (2) or a bus that cannot open (1).

        Each step registers its undo on one `ExitStack`, so they run in reverse: the child
        stopped, the outputs forced safe, the bus and session closed, the files cleaned up."""
        signals = SignalThread(self._on_signal)  # never inside the code a signal interrupts
        signals.start()
        code = EXIT_OK
        started = False
        try:
            with contextlib.ExitStack() as stack:
                stack.callback(self._cleanup)
                try:
                    child_cfg = self._open_hal()
                    session = self._open_session()
                except StartRefused as exc:
                    return exc.code
                stack.callback(self._close_session, session)
                self.bus = SupervisorBus(
                    session, self.config, world=sim_port(self.world), on_presence=self._on_presence
                )
                stack.callback(self.bus.close)
                stack.callback(self._force_safe)
                self.guard = self._start_guard()
                stack.callback(self.guard.stop)
                stack.callback(self._stop_child)
                started = True
                zenoh_json = child_config(self.zenoh.zenoh_config, self.private, self.hang_s)
                self._write_child_files(child_cfg, zenoh_json)
                self.bus.start()
                log.info(
                    "event=supervisor_started id=%s hal=%s private=%s",
                    self.config.machine.id,
                    self.config.hal.backend,
                    self.private,
                )
                code = self._loop()
        finally:
            if started:
                repeated = self.signals_repeated
                log.info(
                    "event=supervisor_stopped code=%d restarts=%d%s",
                    code,
                    self.generation - 1,
                    f" signals_repeated={repeated}" if repeated else "",
                )
            signals.close(then=self.signals_after)
        return code

    def _open_hal(self) -> MachineConfig:
        """`_prepare_hal`, its failures said as `run` says them (a refused start, code 2)."""
        try:
            return self._prepare_hal()
        except HalConfigError as exc:  # the IO map, image or config: fatal, said as `run` says it
            for f in exc.findings:
                print(finding_line("machine", f), file=sys.stderr)
            log.error("event=supervisor_hal_failed error=%r", str(exc))
            raise StartRefused(EXIT_CONFIG, str(exc)) from exc
        except (HalError, OSError, ValueError) as exc:
            log.error("event=supervisor_hal_failed error=%r", str(exc))
            raise StartRefused(EXIT_CONFIG, str(exc)) from exc

    def _open_session(self) -> zbus.Session:
        """The router session; refused (2) without the credentials its profile needs, (1)
        when Zenoh cannot open it."""
        try:
            z = self.zenoh
            conf = router_config(z.zenoh_config, z.listen, z.connect, self.private, self.hang_s)
            if requires_credentials(conf) and not os.environ.get(env_name(MACHINE, "USER")):
                log.error(
                    "event=supervisor_no_credentials detail=%r",
                    "the router checks user/password: give the daemon its identity with"
                    f" {env_name(MACHINE, 'USER')} and {env_name(MACHINE, 'PASSWORD_FILE')}",
                )
                raise StartRefused(EXIT_CONFIG, "no credentials")
            warn_if_exposed(conf, log)
            return zbus.open_session(conf)
        except CredentialError as exc:
            log.error("event=supervisor_bad_credentials error=%r", str(exc))
            raise StartRefused(EXIT_CONFIG, str(exc)) from exc
        except StartRefused:
            raise
        except Exception as exc:  # zenoh raises plain ZError; the outputs are safe already
            log.error("event=zenoh_open_failed error=%r", str(exc))
            raise StartRefused(EXIT_FAILED, f"zenoh session could not open: {exc}") from exc

    @staticmethod
    def _close_session(session: zbus.Session) -> None:
        if not zbus.close_session(session):
            log.warning("event=zenoh_close_timeout")

    def _prepare_hal(self) -> MachineConfig:
        """The safe-output path (and, with the simulator, the plant); the child's config."""
        o = self.options
        field = open_field(self.config, self.dir, o.plant_dir, o.world_period_s, self.beat_fd)
        self.safe, self.world = field.safe, field.world
        return field.child

    def _write_child_files(self, config: MachineConfig, zenoh_json: str) -> None:
        data = config.model_dump(mode="json", by_alias=True, exclude_none=True)
        write_private(self.dir / "machine.toml", to_toml(data))
        write_private(self.dir / "zenoh-child.json5", zenoh_json)

    @property
    def hang_s(self) -> float:
        """How long a daemon may stay frozen before it is killed (`--hang`)."""
        return self.options.hang_s or max(HANG_S, 3 * self.config.loop.watchdog_limit_s)

    def _start_guard(self) -> OutputGuard:
        """The output guard: outputs safe when the child's scan stops (outputguard.py)."""
        assert self.safe is not None
        guard = OutputGuard(
            self.beat,
            self.safe,
            on_trip=self._on_guard_trip,
            on_hang=lambda stall: self.events.put(Event(Kind.HUNG, stall=stall)),
            hang_s=self.hang_s,
            after_safe=self.world.step_now if self.world is not None else None,
        )
        guard.start()
        return guard

    def _cleanup(self) -> None:
        if self.world is not None:
            self.world.stop()
        if self.safe is not None:
            self.safe.close()
        self.beat.close()
        os.close(self.beat_fd)
        shutil.rmtree(self._sockdir, ignore_errors=True)

    # ------------------------------------------------------------------------- the loop
    def _loop(self) -> int:
        restart_at: float | None = time.monotonic()
        heartbeat = self.config.bus.heartbeat_s
        while True:
            now = time.monotonic()
            if self.child is None and restart_at is not None and now >= restart_at:
                self._spawn()
                restart_at = None
            timeout = heartbeat
            if restart_at is not None:
                timeout = min(timeout, max(0.0, restart_at - now))
            child = self.child
            if child is not None and child.up_since is None and not child.down:
                timeout = min(timeout, max(0.0, child.started + self.options.start_timeout_s - now))
            try:
                event = self.events.get(timeout=timeout)
            except queue.Empty:
                limit = self.options.start_timeout_s
                if (
                    child is not None
                    and not child.down
                    and child.up_since is None
                    and time.monotonic() - child.started >= limit
                ):
                    self._freeze(child, f"the daemon was not up within {limit:g} s")
                    restart_at = self._schedule(child)
                else:
                    self.bus.republish()
                continue
            if event.kind is Kind.STOP:
                return EXIT_OK
            if event.kind is Kind.PRESENCE:
                restart_at = self._presence(event.present) or restart_at
                continue
            if event.kind is Kind.HUNG:
                restart_at = self._hung(event.stall) or restart_at
                continue
            if child is None or event.generation != child.generation or child.down:
                continue  # an exit we already handled (a child we killed as frozen)
            self._went_down(child, describe_exit(event.code))
            if event.code == EXIT_CONFIG:
                log.error("event=child_config_error detail=%r", "not restarting a config error")
                return EXIT_CONFIG
            restart_at = self._schedule(child)

    def _presence(self, present: bool) -> float | None:
        child = self.child
        if child is None or child.down:
            return None
        now = time.monotonic()
        if present:
            if child.up_since is None:
                child.up_since = now
                self.bus.daemon_up()
                log.info(
                    "event=daemon_up generation=%d pid=%d start_s=%.3f",
                    child.generation,
                    child.proc.pid,
                    now - child.started,
                )
            return None
        if child.up_since is None:
            return None  # the token of an earlier child, gone late
        self._freeze(child, "the daemon stopped answering (its liveliness token is gone)")
        return self._schedule(child)

    def _on_guard_trip(self, stall: Stall) -> None:
        """On the guard's thread, the outputs already safe: say so (the daemon, should it
        wake, takes FAULT_HW itself; if it does not, `_hung` follows)."""
        log.error(
            "event=output_guard_trip pid=%d stalled_s=%.4f outputs=safe action=latched"
            " guard_late_s=%.4f detail=%r",
            stall.pid,
            stall.stalled_s,
            stall.guard_late_s,
            stall.outputs(),
        )

    def _hung(self, stall: Stall | None) -> float | None:
        """The child's scan has not cycled for `hang_s`: kill it first (it can no longer
        write), outputs safe, report, restart."""
        child = self.child
        if stall is None or child is None or child.down or child.proc.pid != stall.pid:
            return None
        seen = threads(child.proc.pid)
        with contextlib.suppress(ProcessLookupError):
            child.proc.kill()
        log.error("event=child_threads pid=%d when=hung threads=%r", stall.pid, describe(seen))
        self._went_down(
            child,
            f"the daemon's scan loop stopped cycling {stall.stalled_s:.2f} s ago (outputs"
            f" {stall.outputs()}); killed",
        )
        try:
            child.proc.wait(timeout=self.options.stop_timeout_s)
        except subprocess.TimeoutExpired:  # stuck in the kernel: it dies when that returns
            log.error("event=child_kill_pending pid=%d", child.proc.pid)
        return self._schedule(child)

    def _freeze(self, child: Child, reason: str) -> None:
        """A child that is gone from the bus: outputs safe first, then find out why, then kill."""
        self._force_safe()
        first = threads(child.proc.pid)
        try:
            code = child.proc.wait(timeout=0.1)  # a crash closes its link before the exit shows
        except subprocess.TimeoutExpired:
            self._went_down(child, f"{reason}; killed after {self.options.exit_grace_s:g} s")
            try:
                child.proc.wait(timeout=self.options.exit_grace_s)
            except subprocess.TimeoutExpired:
                # where its threads were then and since, for the log: why it stopped answering
                last = threads(child.proc.pid)
                child.proc.kill()
                log.error(
                    "event=child_threads pid=%d when=gone_from_bus threads=%r since=%r",
                    child.proc.pid,
                    describe(first),
                    describe(last, first),
                )
                child.proc.wait(timeout=self.options.stop_timeout_s)
            return
        self._went_down(child, describe_exit(code))

    def _went_down(self, child: Child, reason: str) -> None:
        t0 = time.monotonic()
        self._force_safe()
        if self.world is not None:
            self.world.step_now()  # the world has seen the relays drop before anyone is told
        safe_s = time.monotonic() - t0
        child.down = True
        self.bus.daemon_down(reason)
        log.error(
            "event=daemon_down generation=%d reason=%r safe_ms=%.2f",
            child.generation,
            reason,
            safe_s * 1e3,
        )

    def _schedule(self, child: Child) -> float:
        lived = time.monotonic() - child.up_since if child.up_since is not None else None
        delay = self.backoff.delay(lived, self.options.stable_s)
        self.child = None
        log.info("event=restart_scheduled in_s=%.2f", delay)
        return time.monotonic() + delay

    # --------------------------------------------------------------------------- helpers
    def _spawn(self) -> None:
        self.generation += 1
        cmd = [
            sys.executable,
            "-m",
            "service.cli",
            "run",
            "--config",
            str(self.dir / "machine.toml"),
            "--zenoh-config",
            str(self.dir / "zenoh-child.json5"),
            "--log-level",
            self.options.log_level,
        ]
        env = {
            **os.environ,
            SUPERVISOR_PID_ENV: str(os.getpid()),
            BEAT_FD_ENV: str(self.beat_fd),
        }
        self.beat.reset()  # the new child's first beat arms the guard
        proc = subprocess.Popen(cmd, env=env, pass_fds=(self.beat_fd,))
        child = Child(proc, self.generation, time.monotonic())
        self.child = child
        log.info("event=child_started generation=%d pid=%d", child.generation, proc.pid)
        NamedThread(
            target=self._reap, args=(child,), name=f"reap-{child.generation}", daemon=True
        ).start()

    def _reap(self, child: Child) -> None:
        code = child.proc.wait()
        self.events.put(Event(Kind.EXITED, child.generation, code=code))

    def _stop_child(self) -> None:
        """SIGTERM (the daemon leaves its outputs safe and closes cleanly), bounded."""
        child = self.child
        if child is None or child.proc.poll() is not None:
            return
        child.down = True
        child.proc.send_signal(signal.SIGTERM)
        try:
            child.proc.wait(timeout=self.options.stop_timeout_s)
        except subprocess.TimeoutExpired:
            log.error("event=child_stop_timeout pid=%d", child.proc.pid)
            child.proc.kill()
            child.proc.wait(timeout=self.options.stop_timeout_s)

    def _force_safe(self) -> None:
        if self.safe is not None:
            self.safe.force_all_outputs_safe()

    def _on_signal(self, signum: int) -> None:
        """SIGTERM or SIGINT, on the signal thread (`SignalThread`): the first one stops the
        supervisor; one more while it stops is only counted."""
        if self._stop_asked:
            self.signals_repeated += 1
            return
        self._stop_asked = True
        log.info("event=signal signal=%s", signal.Signals(signum).name)
        self.events.put(Event(Kind.STOP))

    def _on_presence(self, present: bool) -> None:
        self.events.put(Event(Kind.PRESENCE, present=present))


def run_supervisor(config: MachineConfig, zenoh: DaemonOptions, options: SupervisorOptions) -> int:
    """`machine supervise`: returns the process exit code."""
    if bound_malloc_arenas(config.loop.malloc_arenas):  # before its Zenoh threads start
        log.info("event=malloc_arenas limit=%d", config.loop.malloc_arenas)
    # A Zenoh callback must not keep the GIL for Python's default 5 ms while the output
    # guard wakes to a stall (service/core/runner.py `switch_interval`).
    sys.setswitchinterval(config.loop.switch_interval_s)
    supervisor = Supervisor(config, zenoh, options)
    # The process ends when `run` returns: a signal from then on must not kill it (the
    # default action) before its last log lines are written.
    supervisor.signals_after = signal.SIG_IGN
    return supervisor.run()
