"""The supervisor's child handling: the daemon started as a child process, what becomes of it
heard (its exit, its liveliness token coming and going, its scan hung, no start in time), the
outputs made safe and the machine's bus told when it goes, and a new start after the back-off.

The supervisor (service/supervision/supervisor.py) owns the safe-output path, the bus and the
events queue; `ChildKeeper.keep` is its loop until it is asked to stop."""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from ride_machine.hal.backends import World
from ride_machine.service.bus.supervisor import SupervisorBus
from ride_machine.service.core.scan.beat import BEAT_FD_ENV, BeatReader
from ride_machine.service.core.scan.tuning import SUPERVISOR_PID_ENV
from ride_machine.service.threads import NamedThread

from .outcome import EXIT_CONFIG, EXIT_OK
from .outputguard import Stall
from .procstate import describe, threads
from .restarts import (
    Backoff,
    Child,
    Happening,
    Kind,
    SupervisorOptions,
    describe_exit,
)

log = logging.getLogger("machine.supervisor")

TURN_SLACK_S = 2.0
"""Beyond the waits a turn of `keep` is made of: a look for an exit (0.1 s), the world's step,
the thread's own scheduling on a busy host."""


class ChildKeeper:
    """Keeps one daemon child running: starts it from the files in `files`, and when it goes,
    outputs safe first, then the reason told, then a new start after the back-off."""

    def __init__(
        self,
        options: SupervisorOptions,
        files: Path,
        beat: tuple[BeatReader, int],
        happenings: queue.SimpleQueue[Happening],
        bus: SupervisorBus,
        force_safe: Callable[[], None],
        world: World | None,
        heartbeat_s: float,
    ) -> None:
        self.options = options
        self.files = files
        """Where the child's machine.toml and zenoh-child.json5 are."""
        self.beat, self.beat_fd = beat
        """The record the child stamps every cycle, and its descriptor the child inherits."""
        self.happenings = happenings
        self.bus = bus
        self.force_safe = force_safe
        self.world = world
        self.heartbeat_s = heartbeat_s
        """With nothing heard for this long, the bus republishes the machine's state."""
        self.child: Child | None = None
        self.generation = 0
        self.backoff = Backoff(options.backoff_s, options.backoff_max_s)
        self.turned = time.monotonic()
        """When `keep`'s loop last came round (time.monotonic)."""
        self.turn_limit_s = (
            heartbeat_s + options.exit_grace_s + options.stop_timeout_s + TURN_SLACK_S
        )
        """The longest a turn of `keep` takes while the supervisor is well: the wait for a
        happening, then the longest handling of one (a frozen child's grace and kill)."""

    def turning(self, now: float) -> bool:
        """`keep`'s loop came round within `turn_limit_s` of `now` (from any thread)."""
        return now - self.turned <= self.turn_limit_s

    def keep(self) -> int:
        """Until a `STOP` happening (0) or a child that ends with a config error (2)."""
        restart_at: float | None = time.monotonic()
        while True:
            self.turned = now = time.monotonic()
            if self.child is None and restart_at is not None and now >= restart_at:
                self._spawn()
                restart_at = None
            timeout = self.heartbeat_s
            if restart_at is not None:
                timeout = min(timeout, max(0.0, restart_at - now))
            child = self.child
            if child is not None and child.up_since is None and not child.down:
                timeout = min(timeout, max(0.0, child.started + self.options.start_timeout_s - now))
            try:
                happening = self.happenings.get(timeout=timeout)
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
            if happening.kind is Kind.STOP:
                return EXIT_OK
            if happening.kind is Kind.PRESENCE:
                restart_at = self._presence(happening.present) or restart_at
                continue
            if happening.kind is Kind.HUNG:
                restart_at = self._hung(happening.stall) or restart_at
                continue
            if child is None or happening.generation != child.generation or child.down:
                continue  # an exit we already handled (a child we killed as frozen)
            self._went_down(child, describe_exit(happening.code))
            if happening.code == EXIT_CONFIG:
                log.error("event=child_config_error detail=%r", "not restarting a config error")
                return EXIT_CONFIG
            restart_at = self._schedule(child)

    def stop(self, *, frozen: bool = False) -> None:
        """SIGTERM (the daemon leaves its outputs safe and closes cleanly), bounded; SIGKILL
        at once, outputs forced safe first, for a daemon whose scan has stalled (`frozen`):
        a frozen daemon answers no SIGTERM, and waiting for it outlasts a container's stop."""
        child = self.child
        if child is None or child.proc.poll() is not None:
            return
        child.down = True
        if frozen:
            self.force_safe()
            log.error("event=child_stop_frozen pid=%d action=kill", child.proc.pid)
            child.proc.kill()
            self._await_kill(child, "stop")
            return
        child.proc.send_signal(signal.SIGTERM)
        try:
            child.proc.wait(timeout=self.options.stop_timeout_s)
        except subprocess.TimeoutExpired:
            log.error("event=child_stop_timeout pid=%d", child.proc.pid)
            child.proc.kill()
            self._await_kill(child, "stop")

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
        self._await_kill(child, "hung")
        return self._schedule(child)

    def _freeze(self, child: Child, reason: str) -> None:
        """A child that is gone from the bus: outputs safe first, then find out why, then kill."""
        self.force_safe()
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
                self._await_kill(child, "gone_from_bus")
            return
        self._went_down(child, describe_exit(code))

    def _await_kill(self, child: Child, when: str) -> None:
        """Wait for a killed child, bounded: one stuck in the kernel (D state: a hung disk or
        piControl) dies only when that call returns, and supervision goes on meanwhile (its
        reaper reports the exit; a new child may start before it)."""
        limit = self.options.stop_timeout_s
        try:
            child.proc.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            log.error(
                "event=child_kill_pending pid=%d when=%s waited_s=%g detail=%r",
                child.proc.pid,
                when,
                limit,
                "still running after SIGKILL: stuck in the kernel, it ends when that call returns",
            )

    def _went_down(self, child: Child, reason: str) -> None:
        t0 = time.monotonic()
        self.force_safe()
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

    def _spawn(self) -> None:
        self.generation += 1
        cmd = [
            sys.executable,
            "-m",
            "ride_machine.service.cli",
            "run",
            "--config",
            str(self.files / "machine.toml"),
            "--zenoh-config",
            str(self.files / "zenoh-child.json5"),
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
        self.happenings.put(Happening(Kind.EXITED, child.generation, code=code))
