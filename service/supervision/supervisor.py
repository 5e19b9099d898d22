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
import sys
import tempfile
from pathlib import Path

from ride_machine.common.credentials import MACHINE, CredentialError, env_name
from ride_machine.hal.backends import World
from ride_machine.hal.base import HalConfigError, HalError
from ride_machine.service import bus as zbus
from ride_machine.service.bus.exposure import warn_if_exposed
from ride_machine.service.bus.supervisor import (
    SupervisorBus,
    child_config,
    requires_credentials,
    router_config,
)
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.config.validate import finding_line
from ride_machine.service.core.scan.beat import BeatReader, create_beat_fd
from ride_machine.service.signals import SignalThread

from .assembly import DaemonOptions
from .children import ChildKeeper
from .field import SafeOutputs, open_field
from .malloc import bound_malloc_arenas
from .outcome import EXIT_CONFIG, EXIT_FAILED, EXIT_OK, StartRefused
from .outputguard import OutputGuard, Stall
from .restarts import Happening, Kind, SupervisorOptions
from .sdnotify import Notifier
from .simport import sim_port
from .toml_out import to_toml, write_private

log = logging.getLogger("machine.supervisor")

SUPERVISOR_DIR = "supervisor"
HANG_S = 1.0
"""The default hang limit: what the shipped Zenoh profiles' lease gave before (1 s)."""


class Supervisor:
    """Owns the child daemon, the safe-output path, the router session and (sim) the world."""

    def __init__(
        self, config: MachineConfig, zenoh: DaemonOptions, options: SupervisorOptions
    ) -> None:
        self.config = config
        self.zenoh = zenoh
        self.options = options
        self.dir = Path(config.data_dir).resolve() / SUPERVISOR_DIR
        self.happenings: queue.SimpleQueue[Happening] = queue.SimpleQueue()  # put() is signal-safe
        self._stop_asked = False
        self.signals_repeated = 0
        self.signals_after: signal.Handlers | None = None
        """What SIGTERM and SIGINT get once `run` returns; None: the handlers from before."""
        self.world: World | None = None
        self.safe: SafeOutputs | None = None
        self.bus: SupervisorBus
        self.children: ChildKeeper | None = None
        """The daemon child's keeper (service/supervision/children.py), once the bus is up."""
        self.beat_fd = create_beat_fd()
        self.beat = BeatReader(self.beat_fd)
        """The record the daemon child stamps every cycle (`service.core.scan.beat`)."""
        self.guard: OutputGuard | None = None
        self.notifier = Notifier.from_env()
        """systemd's notify socket (sdnotify.py): READY=1 once a daemon serves, WATCHDOG=1
        while the guard's thread and `keep`'s loop both come round; nothing outside systemd."""
        self._sockdir = Path(tempfile.mkdtemp(prefix="machine-sup-"))
        self.private = f"unixsock-stream/{self._sockdir / 'zenoh.sock'}"

    # ------------------------------------------------------------------------- lifecycle
    def run(self) -> int:
        """Until SIGTERM/SIGINT (0), a config problem (2), or a bus that cannot open or the
        child's files that cannot be written (1).

        Each step registers its undo on one `ExitStack`, so they run in reverse: the child
        stopped, the outputs forced safe, the bus and session closed, the files cleaned up."""
        signals = SignalThread(self._on_signal)  # never inside the code a signal interrupts
        signals.start()
        code = EXIT_OK
        try:
            with contextlib.ExitStack() as stack:
                stack.callback(self._cleanup)
                try:
                    child_cfg = self._open_hal()
                    session = self._open_session()
                    stack.callback(self._close_session, session)
                    zenoh_json = child_config(self.zenoh.zenoh_config, self.private, self.hang_s)
                    self._write_child_files(child_cfg, zenoh_json)
                except StartRefused as exc:
                    return exc.code
                self.bus = SupervisorBus(
                    session, self.config, world=sim_port(self.world), on_presence=self._on_presence
                )
                stack.callback(self.bus.close)
                stack.callback(self._force_safe)
                self.guard = self._start_guard()
                stack.callback(self.guard.stop)
                self.children = children = self._keeper()
                stack.callback(self._stop_child)
                self.bus.start()
                log.info(
                    "event=supervisor_started id=%s hal=%s private=%s",
                    self.config.machine.id,
                    self.config.hal.backend,
                    self.private,
                )
                code = children.keep()
        finally:
            if self.children is not None:  # started
                repeated = self.signals_repeated
                log.info(
                    "event=supervisor_stopped code=%d restarts=%d%s",
                    code,
                    self.children.generation - 1,
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
        """The child's config files, in the private dir beside its socket: only the child reads
        them, and a read-only data dir is the child's STORAGE_FAILED warning (H39), not a
        failed start. Refused (1) where even that dir cannot take them."""
        data = config.model_dump(mode="json", by_alias=True, exclude_none=True)
        try:
            write_private(self._sockdir / "machine.toml", to_toml(data))
            write_private(self._sockdir / "zenoh-child.json5", zenoh_json)
        except OSError as exc:
            log.error("event=supervisor_files_failed dir=%s error=%r", self._sockdir, str(exc))
            reason = f"the child's files could not be written: {exc}"
            raise StartRefused(EXIT_FAILED, reason) from exc

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
            on_hang=lambda stall: self.happenings.put(Happening(Kind.HUNG, stall=stall)),
            hang_s=self.hang_s,
            after_safe=self.world.step_now if self.world is not None else None,
            after_look=self._vouch,
        )
        guard.start()
        return guard

    def _keeper(self) -> ChildKeeper:
        """The daemon child's keeper, with the safe-output path and the bus it tells."""
        return ChildKeeper(
            self.options,
            self._sockdir,
            (self.beat, self.beat_fd),
            self.happenings,
            self.bus,
            self._force_safe,
            self.world,
            self.config.bus.heartbeat_s,
        )

    def _vouch(self, now_ns: int) -> None:
        """After each look of the guard, on its thread: systemd's watchdog is fed while this
        thread runs and `keep`'s loop comes round. Not the daemon's beat: the supervisor acts
        on that itself (`--hang`), and a daemon down between restarts is its job, not a
        reason for systemd to kill the router every Rider is connected to."""
        children = self.children
        if children is not None and children.turning(now_ns / 1e9):
            self.notifier.watchdog(now_ns / 1e9)

    def _stop_child(self) -> None:
        """The child stopped as the supervisor stops: killed at once if its scan has stalled
        (it would answer no SIGTERM; the guard made its outputs safe), else with SIGTERM."""
        assert self.children is not None
        frozen = self.guard is not None and self.guard.stalled()
        self.children.stop(frozen=frozen)

    def _cleanup(self) -> None:
        self.notifier.close()
        if self.world is not None:
            self.world.stop()
        if self.safe is not None:
            self.safe.close()
        self.beat.close()
        os.close(self.beat_fd)
        shutil.rmtree(self._sockdir, ignore_errors=True)

    def _on_guard_trip(self, stall: Stall) -> None:
        """On the guard's thread, the outputs already safe: say so (the daemon, should it
        wake, takes FAULT_HW itself; if it does not, `ChildKeeper._hung` follows)."""
        log.error(
            "event=output_guard_trip pid=%d stalled_s=%.4f outputs=safe action=latched"
            " guard_late_s=%.4f detail=%r",
            stall.pid,
            stall.stalled_s,
            stall.guard_late_s,
            stall.outputs(),
        )

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
        self.happenings.put(Happening(Kind.STOP))

    def _on_presence(self, present: bool) -> None:
        if present:  # a daemon serves: start-up is complete for systemd (said once)
            self.notifier.ready()
        self.happenings.put(Happening(Kind.PRESENCE, present=present))


def run_supervisor(config: MachineConfig, zenoh: DaemonOptions, options: SupervisorOptions) -> int:
    """`machine supervise`: returns the process exit code."""
    if bound_malloc_arenas(config.loop.malloc_arenas):  # before its Zenoh threads start
        log.info("event=malloc_arenas limit=%d", config.loop.malloc_arenas)
    # A Zenoh callback must not keep the GIL for Python's default 5 ms while the output
    # guard wakes to a stall (service/core/scan/runner.py `switch_interval`).
    sys.setswitchinterval(config.loop.switch_interval_s)
    supervisor = Supervisor(config, zenoh, options)
    # The process ends when `run` returns: a signal from then on must not kill it (the
    # default action) before its last log lines are written.
    supervisor.signals_after = signal.SIG_IGN
    return supervisor.run()
