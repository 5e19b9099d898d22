"""The event history written by a process of its own (`[events] process = true`, the default).

Why: on a host with few cores, any thread of the daemon that runs for a millisecond, holding
the GIL or a CPU, delays whoever wakes beside it. Made and written on a thread of the daemon,
the history (20-27 µs of CPU per command, in bursts of a batch) was what made the 1 % slowest
commands take 1.2-1.5 ms (BENCHMARKS.md, section 1, tenth pass). A process has a GIL of its
own, and it gives way between short slices of work (`sched_yield`), so the scheduler runs a
woken command thread at once instead of after the writer's time slice.

`HistoryProcess` is an `EventLog` whose writer thread only sends: what the scan loop and the
commands queue (`emit`, `defer`) goes down a pipe, a batch at a time, as msgpack, to
`python -m ride_machine.service.adapters.history_writer` (the messages:
service/adapters/history_pipe.py; what a queued event, command or line is sent as:
service/adapters/history_items.py). That process makes the events (a command's event and its
log line from its `CommandFacts`) and writes them with an `EventWriter` of its own: the same
batches, retention, failure handling and `storage_failed` records. It loads no pydantic (half
its memory): a command's event is made from its facts as plain JSON, and its settings come as
plain values. It sends back what it wrote (the bus publishes it), its counters and its log
lines (written to the daemon's stderr by the daemon's log writer, so lines never interleave).
Reads stay in the daemon, on a connection of their own: WAL lets them read while the other
process writes.

If the process ends unexpectedly, the events it had not confirmed are counted lost, a new one
is started (at most once a second), and its first write records a `storage_failed` event. It
ends by itself when the daemon does: the pipe closes, it writes what it received and exits.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from ride_machine.schema.diag import EventsDiag
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.held import Held
from ride_machine.service.logfmt import put_text
from ride_machine.service.threads import NamedThread

from .eventdb import Row, claim_writer
from .eventlog import EventLog
from .history_items import batch_items, rows_in
from .history_pipe import (
    BATCH,
    FAILED,
    FLUSH,
    FLUSHED,
    LOG,
    WROTE,
    Item,
    encode,
    messages,
    write_all,
)

log = logging.getLogger(__name__)

RESPAWN_S = 1.0
"""A history process that ended is started again after this long; one that keeps ending
within `STEADY_S` of its start waits twice as long each time, up to `RESPAWN_MAX_S`."""
RESPAWN_MAX_S = 30.0
STEADY_S = 10.0
PYTHON = sys.executable
"""The interpreter the history process runs on: the daemon's own."""


class HistoryProcess(EventLog):
    """An `EventLog` whose events are made and written by `python -m
    ride_machine.service.adapters.history_writer`."""

    def __init__(self, path: Path, machine_id: str, settings: EventsSection, **kw: Any) -> None:
        super().__init__(path, machine_id, settings, **kw)
        self._proc: subprocess.Popen[bytes] | None = None
        self._send_lock = threading.Lock()
        self._state = threading.Lock()
        """Guards the counters below and the ones `EventLog` keeps, set from two threads."""
        self._receiver: threading.Thread | None = None
        self._spawned_at = -RESPAWN_S
        self._respawn_s = RESPAWN_S
        self._last_try = False
        self._cut_short = False
        """`close` killed the process at its deadline."""
        self._sending = False
        self._sent = 0
        """Events sent to the current process."""
        self._settled = 0
        """Of those, written, dropped or counted lost by it (its latest word)."""
        self._base = (0, 0, 0)
        """written, lost, failures of the processes before the current one, and of this side."""
        self._child_dropped = 0
        self._forward_dropped = 0
        """Of `dropped` (here), those told to the process (it records them as `events_dropped`)."""
        self._pending_failure: tuple[str, int] | None = None
        self._flushes: dict[int, threading.Event] = {}
        self._tokens = itertools.count(1)
        self._retry: list[Item] = []
        """A batch whose send found the process gone (no reader: none of it was taken), for
        the next process; only the writer thread changes it."""

    # ------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open (or set aside and replace) the database here, as `EventLog` does, so that
        `previous_stop_clean` is known at once; then start the process that writes it.

        Read only once the log's previous writer has let go (`claim_writer`, then let go for
        this daemon's own process to claim): a killed daemon's history process still writes
        what it was sent, its `daemon_start` among it, and read before that the last run
        looked clean (a run under load: `previous_stop_clean` True after a SIGKILL)."""
        writer = self.writer
        fd, _ = claim_writer(self.path, self.writer_wait_s)  # the process says if it is held
        if fd is not None:
            os.close(fd)
        self.previous_stop_clean = writer.open_or_replace(self.wall())
        writer.release()
        self._pending_failure, writer.failure = writer.failure, None
        self._base = (0, self.lost, self.failures)
        self._spawn()
        self._start_threads()

    def _spawn(self) -> bool:
        self._spawned_at = time.monotonic()
        root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        level = logging.getLevelName(logging.getLogger().getEffectiveLevel()).lower()
        try:
            proc = subprocess.Popen(
                [
                    PYTHON,
                    "-m",
                    "ride_machine.service.adapters.history_writer",
                    str(self.path),
                    self.machine_id,
                    self.settings.model_dump_json(),
                    level,
                ],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                bufsize=0,
                env=env,
            )
        except OSError as exc:  # e.g. out of memory or of processes: tried again, less often
            self._respawn_s = min(RESPAWN_MAX_S, self._respawn_s * 2)
            self._lose(0, f"cannot start the event writer process: {exc}")
            return False
        with self._state:
            self._proc = proc
            self._sent = self._settled = 0
            self._child_dropped = 0
        self._receiver = NamedThread(
            target=self._receive, args=(proc,), name="eventlog-recv", daemon=True
        )
        self._receiver.start()
        if self._pending_failure is not None:
            error, lost = self._pending_failure
            self._pending_failure = None
            self._send(proc, [FAILED, error, lost])
        return True

    def close(self, timeout: float = 2.0) -> None:
        """Send what is queued, let the process write it and end; never longer than
        `timeout` (then the process is killed, and what it had not written is counted lost)."""
        deadline = time.monotonic() + timeout
        self._stop()
        if self._thread is not None:
            self._thread.join(max(0.0, deadline - time.monotonic()))
        proc = self._proc
        if proc is not None:
            with contextlib.suppress(OSError):
                if proc.stdin is not None:
                    proc.stdin.close()
            try:
                proc.wait(max(0.05, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._cut_short = True
                self._last_try = True  # no new process for what a blocked send still holds
                proc.kill()
                proc.wait()
        if self._receiver is not None:  # it counts what a killed process had not written
            self._receiver.join(max(0.5, deadline - time.monotonic()))
        self._reader.join(max(0.0, deadline - time.monotonic()))

    # ---------------------------------------------------------------------------- sending
    def _run(self) -> None:
        while True:
            self._gather(1.0)  # a batch per wake-up, as `EventLog` gathers
            proc = self._proc
            if proc is None and not self._respawn():
                with self._lock:
                    if not self._stopping:
                        continue
                    rest = sum(rows_in(entry) for entry in self._items) + len(self._retry)
                    self._items.clear()
                    self._retry = []
                if rest:
                    self._lose(rest, "the event writer process is not running")
                return
            with self._lock:
                batch = list(self._items)
                self._items.clear()
                self._wake.clear()
                self._deferred = 0
                self._sending = bool(batch or self._retry)
                dropped = self.dropped - self._forward_dropped
                self._forward_dropped = self.dropped
                stopping = self._stopping
            try:
                if batch or dropped or self._retry:
                    self._send_batch(batch, dropped)
            except Exception as exc:  # noqa: BLE001 - one bad batch must not end the history
                self._lose(len(batch), f"event writer failed: {exc!r}", exc)
            finally:
                self._sending = False
            if stopping:
                with self._lock:
                    if not self._items and not self._retry:
                        return

    def _respawn(self) -> bool:
        """A new process once the pause since the last start has passed (events wait in the
        queue meanwhile; a full queue drops and counts them); on `close`, one more try at
        once for what is still queued (the daemon's last events)."""
        with self._lock:
            stopping, queued = self._stopping, bool(self._items or self._retry)
        if stopping:
            if not queued or self._last_try:
                return False
            self._last_try = True
            return self._spawn()
        wait = self._spawned_at + self._respawn_s - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, 0.1))
            self._wake.set()  # come back for the queue
            return False
        return self._spawn()

    def _send_batch(self, batch: list[Row | Held | str], dropped: int) -> None:
        items, self._retry = self._retry, []
        for entry in batch:
            try:
                items.extend(batch_items(entry))
            except Exception as exc:  # noqa: BLE001 - one bad record must not stop the batch
                self._lose(1, f"event making failed: {exc!r}", exc)
        proc = self._proc
        if proc is None or not self._send(proc, [BATCH, dropped, items]):
            # It ended before the receiver saw it go: these wait for the next process, as
            # events emitted after it went do (its unconfirmed ones are counted lost there).
            self._retry = items
            with self._lock:  # the next process is told of these drops instead
                self._forward_dropped -= dropped
            receiver = self._receiver  # that process's: only this thread starts another
            if proc is not None and receiver is not None:
                receiver.join(1.0)  # it reaps the process and counts what it lost, then ends
            return
        with self._state:
            current = proc is self._proc
            if current:
                self._sent += len(items)
        if not current:  # it ended while this batch went: whatever it received is unconfirmed
            self._lose(len(items), "the event writer process ended")

    def _send(self, proc: subprocess.Popen[bytes], message: list[Any]) -> bool:
        data = encode(message)
        with self._send_lock:
            pipe = proc.stdin
            if pipe is None:
                return False
            try:
                write_all(pipe, data)
            except (OSError, ValueError):  # ended, or closed by `close`
                return False
        return True

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until everything queued so far is written (tests, reads and shutdown)."""
        deadline = time.monotonic() + timeout
        self._wake.set()
        if not self._drained(
            deadline, lambda: not self._items and not self._sending and not self._retry
        ):
            return False
        proc = self._proc
        if proc is None:
            return False
        token = next(self._tokens)
        done = self._flushes[token] = threading.Event()
        try:
            if not self._send(proc, [FLUSH, token, max(0.0, deadline - time.monotonic())]):
                return False
            return done.wait(max(0.0, deadline - time.monotonic())) and proc is self._proc
        finally:
            self._flushes.pop(token, None)

    def _unsettled(self) -> bool:
        return bool(self._items or self._retry) or self._sending or self._sent != self._settled

    # -------------------------------------------------------------------------- receiving
    def _receive(self, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout is not None
        try:
            for message in messages(proc.stdout.fileno()):
                self._handle(proc, message)
        except Exception as exc:  # a garbled pipe ends this process
            log.error("event=events_process_garbled error=%r", str(exc), exc_info=exc)
            proc.kill()
        code = proc.wait()
        self._ended(proc, code)

    def _handle(self, proc: subprocess.Popen[bytes], message: tuple[Any, ...]) -> None:
        tag = message[0]
        if tag == WROTE:
            _, rows, status = message
            self._status(proc, status)
            if rows:
                self.writer.publish(list(rows))
        elif tag == FLUSHED:
            _, token, status = message
            self._status(proc, status)
            done = self._flushes.get(token)
            if done is not None:
                done.set()
        elif tag == LOG:
            put_text(message[1])

    def _status(self, proc: subprocess.Popen[bytes], status: tuple[Any, ...]) -> None:
        written, lost, failures, last_error, dropped, settled = status
        with self._state:
            if proc is not self._proc:
                return
            base_written, base_lost, base_failures = self._base
            self.written = base_written + written
            self.lost = base_lost + lost
            self.failures = base_failures + failures
            if last_error is not None:
                self.last_error = last_error
            self._child_dropped = dropped
            self._settled = settled

    def _ended(self, proc: subprocess.Popen[bytes], code: int) -> None:
        """The process is gone: what it had not confirmed is lost (unless it ended cleanly
        on `close` with everything written)."""
        with self._state:
            if proc is not self._proc:
                return
            unconfirmed = self._sent - self._settled
            self._proc = None
            self._base = (self.written, self.lost, self.failures)
            self._sent = self._settled = 0
        for done in list(self._flushes.values()):
            done.set()  # a flush waiting on it learns at once (and reads `_unsettled`)
        if self._stopping and code == 0 and not unconfirmed:
            return
        lived = time.monotonic() - self._spawned_at
        self._respawn_s = (
            RESPAWN_S if lived >= STEADY_S else min(RESPAWN_MAX_S, self._respawn_s * 2)
        )
        error = f"the event writer process ended with exit code {code}"
        if self._cut_short:  # what held it up (a locked or stalled disk) says more
            error = (
                f"the event writer process was stopped at the shutdown deadline: {self.last_error}"
            )
        self._lose(unconfirmed, error)
        self._pending_failure = (error, unconfirmed)
        self._wake.set()

    def _lose(self, lost: int, error: str, exc: BaseException | None = None) -> None:
        with self._state:
            written, base_lost, failures = self._base
            self._base = (written, base_lost + lost, failures + 1)
            self.lost += lost
            self.failures += 1
            self.last_error = error
        log.error("event=events_write_failed error=%r lost=%d", error, lost, exc_info=exc)

    def diag(self) -> EventsDiag:
        d = super().diag()
        return d.model_copy(update={"dropped": self.dropped + self._child_dropped})
