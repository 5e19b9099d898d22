"""The event history written by a process of its own (`[events] process = true`, the default):
why, and how it behaves, is docs/events.md, "Written by a process of its own".

`HistoryProcess` is an `EventLog` whose writer thread only sends: what the scan loop and the
commands queue (`emit`, `defer`) goes down a pipe, a batch at a time, as msgpack, to `python -m
ride_machine.service.adapters.history_writer` (the messages and the pipe's ends:
history_pipe.py; what a queued event, command or line is sent as: history_items.py). That
process makes the events and writes them with an `EventWriter` of its own, and sends back what
it wrote (the bus publishes it), its counters and its log lines. Reads stay in the daemon, on a
connection of their own (WAL). A process that ends, or stalls and is killed, costs the routine
events it had not confirmed; what it had not confirmed of the safety record goes to the next
one (what the daemon keeps of each process: history_ledger.py; when a new one starts:
history_spawn.py). `close` kills it at its deadline and puts what it held in the file the next
start writes first, as `EventLog.close` does.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ride_machine.schema.diag import EventsDiag
from ride_machine.service.config.model import EventsSection
from ride_machine.service.core.history.held import Held
from ride_machine.service.logfmt import put_text
from ride_machine.service.threads import NamedThread

from .eventdb import Row, claim_writer
from .eventlog import EventLog, without_lines
from .history_items import batch_items
from .history_ledger import Ledger, events_in, safety, stalled_words
from .history_pipe import (
    BATCH,
    FAILED,
    FLUSH,
    FLUSHED,
    LOG,
    WROTE,
    Item,
    Outlet,
    Sent,
    messages,
)
from .history_spawn import Pause, start_writer
from .history_writer import make_rows

log = logging.getLogger(__name__)

KILL_MARGIN_S = 0.5
"""Of `close`'s time, what is kept to kill a process whose pipe stayed full and spill what it
had not confirmed: a send gives up this long before the deadline."""


class HistoryProcess(EventLog):
    """An `EventLog` whose events are made and written by `python -m
    ride_machine.service.adapters.history_writer`."""

    def __init__(self, path: Path, machine_id: str, settings: EventsSection, **kw: Any) -> None:
        super().__init__(path, machine_id, settings, **kw)
        self._proc: subprocess.Popen[bytes] | None = None
        self._outlet: Outlet | None = None
        """The current process's stdin (set before `_proc`)."""
        self._state = threading.Lock()
        """Guards the counters below and the ones `EventLog` keeps, set from two threads."""
        self._receiver: threading.Thread | None = None
        self._pause = Pause()
        self._last_try = False
        self._cut_short = False
        """`close` killed the process at its deadline."""
        self._sending = False
        self._ledger = Ledger(0.0)
        """The current process's account: what it was sent and has settled (`_state`)."""
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
        self._again = 0
        """Of `_retry`, the first ones sent before to a process that ended (`BATCH`'s `again`)."""
        self._resend: list[Item] = []
        """The safety events a process that ended had not confirmed, for the next one (or
        `close`'s spill)."""
        self._killed: subprocess.Popen[bytes] | None = None
        """The process killed as stalled."""
        self._send_until = float("inf")
        """Set by `close`: a send waiting for room gives up then."""
        self._ended_clean = False
        """The last process ended on `close` with everything written: it spilled what it held."""

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
        self._pause.started(time.monotonic())
        try:
            proc = start_writer(self.path, self.machine_id, self.settings.model_dump_json())
        except OSError as exc:
            self._pause.failed()
            self._lose(0, f"cannot start the event writer process: {exc}")
            return False
        assert proc.stdin is not None
        outlet = self._outlet = Outlet(proc.stdin)
        with self._state:
            self._proc = proc
            self._ledger = Ledger(time.monotonic())
            self._child_dropped = 0
        self._receiver = NamedThread(
            target=self._receive, args=(proc,), name="eventlog-recv", daemon=True
        )
        self._receiver.start()
        if self._pending_failure is not None:
            error, lost = self._pending_failure
            self._pending_failure = None
            outlet.send([FAILED, error, lost], self._giving_up(proc))
        return True

    def close(self, timeout: float = 2.0) -> None:
        """Send what is queued, let the process write it and end; never longer than
        `timeout` (then the process is killed: what it had not confirmed is counted lost, and
        its safety events, with what was not sent, go to the file the next start writes)."""
        deadline = time.monotonic() + timeout
        self._send_until = deadline - min(KILL_MARGIN_S, timeout / 2)
        self._stop()
        ended = self._join(deadline)
        proc, outlet = self._proc, self._outlet
        if proc is not None and outlet is not None:
            self._end(proc, outlet, deadline)
        if self._receiver is not None:  # it counts what a killed process had not written
            self._receiver.join(max(0.5, deadline - time.monotonic()))
        self._reader.join(max(0.0, deadline - time.monotonic()))
        if ended and not self._ended_clean:  # one that ended cleanly spilled what it held
            self._spill(self._leftovers())

    def _end(self, proc: subprocess.Popen[bytes], outlet: Outlet, deadline: float) -> None:
        """Close its pipe (it writes what it has and exits); killed at `deadline`."""
        outlet.close(deadline - time.monotonic())
        try:
            proc.wait(max(0.05, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            self._cut(proc)
            with contextlib.suppress(subprocess.TimeoutExpired):  # a disk that never answers
                proc.wait(KILL_MARGIN_S)

    def _cut(self, proc: subprocess.Popen[bytes]) -> None:
        """End it at the stop's deadline; no new process for what it held (that is spilled)."""
        self._cut_short = True
        self._last_try = True
        proc.kill()

    def _leftovers(self) -> list[Row | Held]:
        """What no process took: the safety events sent to one that did not confirm them,
        then what was not sent (as rows; log lines written now)."""
        with self._state:
            _, unconfirmed = self._ledger.unconfirmed()  # its routine ones: counted at its end
            items, self._resend = self._resend + unconfirmed, []
        items, self._retry = items + self._retry, []
        return [*make_rows(items), *without_lines(self._take_all())]

    def _spill(self, queued: list[Row | Held]) -> None:
        """As `EventLog`'s, with the loss no process recorded, only the drops none was told of
        (the processes record theirs), and what the file still holds: the previous run's
        events a process resumed and never wrote, or a killed process's own spill."""
        self.writer.failure, self._pending_failure = self._pending_failure, None
        self.writer.dropped_recorded = self._forward_dropped
        kept = self.writer.resume_unwritten()
        super()._spill([*kept, *queued])

    # ---------------------------------------------------------------------------- sending
    def _run(self) -> None:
        while True:
            self._gather(1.0)  # a batch per wake-up, as `EventLog` gathers
            proc = self._proc
            if proc is None:
                self._take_resend()
                if not self._respawn():
                    if self._stopping:
                        return  # what is left goes to `close`'s spill
                    continue
            elif self._stall_due(proc, sending=False):
                self._kill_stalled(proc, 0)
                if self._stopping:
                    return
                self._await_end()
                continue
            with self._lock:
                batch = list(self._items)
                self._items.clear()
                self._wake.clear()
                self._deferred = 0
                self._sending = bool(batch or self._retry)
                dropped = self.dropped - self._forward_dropped
                self._forward_dropped = self.dropped
                stopping = self._stopping
            sent = Sent.TAKEN
            try:
                if batch or dropped or self._retry:
                    sent = self._send_batch(batch, dropped)
            except Exception as exc:  # noqa: BLE001 - one bad batch must not end the history
                self._lose(len(batch), f"event writer failed: {exc!r}", exc)
            finally:
                self._sending = False
            if sent is Sent.LATE and self._stopping:
                return  # the process is ended at once: what it held goes to `close`'s spill
            if stopping:
                with self._lock:
                    if not self._items and not self._retry:
                        return

    def _take_resend(self) -> None:
        """The safety events an ended process had not confirmed, first for the next one."""
        with self._state:
            resend, self._resend = self._resend, []
        if resend:
            self._retry = resend + self._retry
            self._again += len(resend)

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
        wait = self._pause.left(time.monotonic())
        if wait > 0:
            time.sleep(min(wait, 0.1))
            self._wake.set()  # come back for the queue
            return False
        return self._spawn()

    def _send_batch(self, batch: list[Row | Held | str], dropped: int) -> Sent:
        items, self._retry = self._retry, []
        again, self._again = self._again, 0
        for entry in batch:
            try:
                items.extend(batch_items(entry))
            except Exception as exc:  # noqa: BLE001 - one bad record must not stop the batch
                self._lose(1, f"event making failed: {exc!r}", exc)
        events = events_in(items)
        proc, outlet = self._proc, self._outlet
        sent = Sent.GONE
        if proc is not None and outlet is not None:
            with self._state:
                self._ledger.giving(time.monotonic())
            sent = outlet.send([BATCH, dropped, items, again], self._giving_up(proc))
        if sent is Sent.TAKEN:
            self._track(proc, items, events)
            return sent
        # None of it reached a reader whole: these wait for the next process, as events
        # emitted after this one went do (its unconfirmed ones are counted lost there).
        self._retry, self._again = items, again
        with self._lock:  # the next process is told of these drops instead
            self._forward_dropped -= dropped
        if proc is None:
            return sent
        if sent is Sent.LATE:
            if self._stall_due(proc, sending=True):
                self._kill_stalled(proc, events)
            else:
                self._cut(proc)  # `close`'s deadline
            if self._stopping:
                return sent
        self._await_end()
        return sent

    def _track(self, proc: subprocess.Popen[bytes] | None, items: list[Item], events: int) -> None:
        """`items`, taken by `proc`, wait for its word; the safety events among them are kept
        until then, for the next process should this one end first."""
        with self._state:
            if proc is self._proc:
                self._ledger.took(items)
                return
            # It ended while this batch went: whatever it received is unconfirmed.
            resend = safety(items)
            self._resend += resend
        self._lose(events - len(resend), "the event writer process ended")

    def _await_end(self) -> None:
        """Let the receiver reap an ended (or killed) process and count what it lost; only
        this thread starts another."""
        receiver = self._receiver
        if receiver is not None:
            receiver.join(1.0)

    def _giving_up(self, proc: subprocess.Popen[bytes]) -> Callable[[], bool]:
        """When the writer thread's send stops waiting: `proc` stalled, or `close`'s deadline."""
        return lambda: self._stall_due(proc, sending=True) or time.monotonic() >= self._send_until

    def _stall_due(self, proc: subprocess.Popen[bytes], *, sending: bool) -> bool:
        """`proc` has confirmed nothing for `STALL_S` while events sent to it (or being sent)
        wait."""
        with self._state:
            return proc is self._proc and self._ledger.stalled(time.monotonic(), sending=sending)

    def _kill_stalled(self, proc: subprocess.Popen[bytes], sending: int) -> None:
        """Kill a stalled process (once): its end is any process's end (`_ended`)."""
        with self._state:
            if self._killed is proc:
                return
            self._killed = proc
            pending = self._ledger.sent - self._ledger.settled + sending
            self.last_error = f"the event writer process stalled: {stalled_words()}"
        if self._stopping:
            self._last_try = True  # what it held is spilled, not sent to a new one
        log.error("event=events_process_stalled pid=%d pending=%d", proc.pid, pending)
        proc.kill()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until everything queued so far is written (tests, reads and shutdown)."""
        deadline = time.monotonic() + timeout
        self._wake.set()
        if not self._drained(deadline, lambda: not self._unsettled_here()):
            return False
        proc, outlet = self._proc, self._outlet
        if proc is None or outlet is None:
            return False
        token = next(self._tokens)
        done = self._flushes[token] = threading.Event()
        until = min(deadline, self._send_until)
        message = [FLUSH, token, max(0.0, deadline - time.monotonic())]
        try:  # short: written whole or not at all (`write_within`), so giving up is safe
            if outlet.send(message, lambda: time.monotonic() >= until) is not Sent.TAKEN:
                return False
            return done.wait(max(0.0, deadline - time.monotonic())) and proc is self._proc
        finally:
            self._flushes.pop(token, None)

    def _unsettled_here(self) -> bool:
        """Events not sent yet (queued, being sent, or waiting for the next process)."""
        return bool(self._items or self._retry or self._resend) or self._sending

    def _unsettled(self) -> bool:
        return self._unsettled_here() or self._ledger.sent != self._ledger.settled

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
            self._ledger.said(settled, time.monotonic())
            base_written, base_lost, base_failures = self._base
            self.written = base_written + written
            self.lost = base_lost + lost
            self.failures = base_failures + failures
            if last_error is not None:
                self.last_error = last_error
            self._child_dropped = dropped

    def _ended(self, proc: subprocess.Popen[bytes], code: int) -> None:
        """The process is gone: what it had not confirmed is lost (unless it ended cleanly
        on `close` with everything written)."""
        with self._state:
            if proc is not self._proc:
                return
            unconfirmed, resend = self._ledger.unconfirmed()
            self._resend += resend  # the next process writes them
            self._proc = None
            self._base = (self.written, self.lost, self.failures)
        for done in list(self._flushes.values()):
            done.set()  # a flush waiting on it learns at once (and reads `_unsettled`)
        if self._stopping and code == 0 and not unconfirmed and not resend:
            self._ended_clean = True
            return
        self._pause.ended(time.monotonic())
        error = f"the event writer process ended with exit code {code}"
        if self._killed is proc:
            error = f"the event writer process stalled and was killed: {stalled_words()}"
        elif self._cut_short:  # what held it up (a locked or stalled disk) says more
            error = "the event writer process was stopped at the shutdown deadline"
            if self.last_error is not None:
                error = f"{error}: {self.last_error}"
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
