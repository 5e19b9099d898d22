"""`Bridge`: one Rider session on a background thread that feeds machine updates to the UI.

Zenoh callbacks only enqueue samples; the bridge thread decodes them, asks for a fresh
picture (IO, axes, diagnostics) whenever the machine comes (back), and hands every update to
`sink`. Nothing a browser does can block it.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
from pydantic import BaseModel

from rider.client import AmbiguousMachine, CommandRefused, NoMachine, Rider, RiderError
from rider.ui.view import LOST_AFTER_S, MachineFound, Note, Presence, Update
from schema.axes import AxisRecord
from schema.codec import DecodeError, Format, decode
from schema.commands import Command, Reply, Session
from schema.diag import CycleDiag
from schema.io import IoValue
from schema.status import Status

log = logging.getLogger("rider.ui")

WATCHED = ("status", "io/**", "axis/**", "diag/cycle")
POLL_S = 0.25


class NotReady(RiderError):
    """The bridge has no session or no machine yet."""


class Bridge:
    """Owns the Rider session; `start()` runs it on a thread, `stop()` closes it (bounded)."""

    def __init__(
        self, rider: Rider, sink: Callable[[Update], None], *, retry_s: float = 1.0
    ) -> None:
        self.rider = rider
        self.sink = sink
        self.retry_s = retry_s
        self.machine_id: str | None = None
        self._stop = threading.Event()
        self._samples: queue.Queue[tuple[bool, zenoh.Sample]] = queue.Queue(maxsize=8192)
        self._subs: list[Any] = []
        self._opened = False
        self._thread = threading.Thread(target=self._run, name="rider-ui-bridge", daemon=True)

    # ---------------------------------------------------------------------------- control
    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float) -> bool:
        """Ask the thread to close the session; True if it finished within `timeout`."""
        self._stop.set()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def command(self, command: Command, session: Session | None = None) -> Reply:
        """Send one command; a refusal is returned as its `Reply`, a timeout raises."""
        if not self._opened or self.machine_id is None:
            raise NotReady("not connected to a machine yet")
        try:
            if command is Command.START:
                return self.rider.start(session)
            return self.rider.command(command)
        except CommandRefused as exc:
            return exc.reply

    # ----------------------------------------------------------------------------- thread
    def _run(self) -> None:
        try:
            if not (self._open() and self._find_machine()):
                return
            while not self._stop.is_set():
                try:
                    self._follow()
                except zenoh.ZError as exc:
                    # Keep serving the page: say what broke, then declare everything again.
                    log.error("event=ui_bridge_error error=%r", str(exc))
                    self._emit(Note(f"Zenoh error: {exc}; retrying"))
                    self._undeclare()
                    self._stop.wait(self.retry_s)
        finally:
            self._close()

    def _open(self) -> bool:
        while not self._stop.is_set():
            try:
                self.rider.open()
            except zenoh.ZError as exc:
                self._emit(Note(f"cannot open the Zenoh session: {exc}"))
                self._stop.wait(self.retry_s)
                continue
            self._opened = True
            log.info("event=ui_session_open rider=%s", self.rider.rider_id)
            return True
        return False

    def _find_machine(self) -> bool:
        while not self._stop.is_set():
            try:
                self.machine_id = self.rider.machine_id
            except NoMachine:
                self._emit(Note("no machine is alive on the network yet; searching…"))
            except AmbiguousMachine as exc:
                self._emit(Note(str(exc)))
            else:
                self._emit(MachineFound(self.machine_id))
                log.info("event=ui_machine machine=%s", self.machine_id)
                return True
            self._stop.wait(self.retry_s)
        return False

    def _follow(self) -> None:
        session, base = self.rider.session, self.rider.base
        for key in WATCHED:
            self._subs.append(
                session.declare_subscriber(f"{base}/{key}", lambda s: self._enqueue(False, s))
            )
        self._subs.append(
            session.liveliness().declare_subscriber(
                f"{base}/alive", lambda s: self._enqueue(True, s), history=True
            )
        )
        last_status = time.monotonic() if self._refresh() else None
        while not self._stop.is_set():
            try:
                presence, sample = self._samples.get(timeout=POLL_S)
            except queue.Empty:
                continue
            if presence:
                alive = sample.kind == zenoh.SampleKind.PUT
                if not alive:
                    last_status = None  # a machine that comes back gets a full refresh
                self._emit(Presence(alive))
                continue
            update = _decode(sample)
            if update is None:
                continue
            if isinstance(update, Status):
                now = time.monotonic()
                back = last_status is None or now - last_status > LOST_AFTER_S
                last_status = now
                # IO is published on change only: after a gap, ask for all of it again. The
                # fresh status comes last, so the page is whole when it shows the link up.
                if back and self._refresh():
                    continue
            self._emit(update)

    def _refresh(self) -> bool:
        """Ask for the whole picture (IO, axes, diagnostics, then status); True if the
        machine answered with its status."""
        rider = self.rider
        reads: list[Callable[[], object]] = [rider.io, rider.axes, rider.diag, rider.status]
        got_status = False
        for read in reads:
            if self._stop.is_set():
                return False
            try:
                got = read()
            except RiderError as exc:
                log.info("event=ui_refresh_failed error=%r", str(exc))
                continue
            for update in got if isinstance(got, list) else [got]:
                if isinstance(update, Status | IoValue | AxisRecord | CycleDiag):
                    self._emit(update)
                    got_status = got_status or isinstance(update, Status)
        return got_status

    def _enqueue(self, presence: bool, sample: zenoh.Sample) -> None:
        # Zenoh's callback thread: never block it; a full queue drops the sample.
        with contextlib.suppress(queue.Full):
            self._samples.put_nowait((presence, sample))

    def _emit(self, update: Update) -> None:
        try:
            self.sink(update)
        except RuntimeError:
            self._stop.set()  # the event loop is gone: the server is shutting down

    def _undeclare(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()
        self._subs.clear()

    def _close(self) -> None:
        self._undeclare()
        if self._opened:
            self._opened = False
            self.rider.close()
            log.info("event=ui_session_closed")


def _decode(sample: zenoh.Sample) -> Update | None:
    """A published sample as its wire model; None for keys we do not show or bad data."""
    key = str(sample.key_expr)
    model: type[BaseModel]
    if key.endswith("/status"):
        model = Status
    elif "/io/" in key:
        model = IoValue
    elif "/axis/" in key:
        model = AxisRecord
    elif key.endswith("/diag/cycle"):
        model = CycleDiag
    else:
        return None
    fmt = Format.JSON if str(sample.encoding).startswith(Format.JSON) else Format.MSGPACK
    try:
        update = decode(model, sample.payload.to_bytes(), fmt)
    except DecodeError as exc:
        log.warning("event=ui_bad_sample key=%s error=%r", key, exc.error.message)
        return None
    assert isinstance(update, Status | IoValue | AxisRecord | CycleDiag)
    return update
