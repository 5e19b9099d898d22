"""`Bridge`: one Rider session on a background thread that feeds machine updates to the UI.

The Rider's subscription only enqueues decoded updates (on Zenoh's thread); the bridge thread
asks for a fresh picture (IO, axes, diagnostics) whenever the machine comes (back), and hands
every update to `sink`. Nothing a browser does can block it.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable

from ride_machine.rider.client import (
    AmbiguousMachine,
    BusError,
    CommandRefused,
    NoMachine,
    Rider,
    RiderError,
    Subscription,
)
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import CalibrationRecord
from ride_machine.schema.commands import Command, Reply, Session
from ride_machine.schema.completion import Completion
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.events import Event, EventQuery
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import Status

from .view import (
    DEFAULT_HEARTBEAT_S,
    MachineFound,
    Note,
    Presence,
    Update,
    lost_after,
)

log = logging.getLogger("rider.ui")

WATCHED = ("status", "io/**", "axis/**", "diag/cycle", "done/**", "calibration")
POLL_S = 0.25
NOTICE_WAIT_S = 1.0
"""A motion the status shows ended, and no notice of it came within this: the bridge asks for
it (`done/<id>`). A notice is published once, dropped like any update on a congested link."""


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
        self._updates: queue.Queue[Update] = queue.Queue(maxsize=8192)
        self._sub: Subscription | None = None
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

    def events(self, query: EventQuery) -> list[Event]:
        """The machine's event history `query` selects (newest last)."""
        if not self._opened or self.machine_id is None:
            raise NotReady("not connected to a machine yet")
        return self.rider.events(query)

    # ----------------------------------------------------------------------------- thread
    def _run(self) -> None:
        try:
            if not (self._open() and self._find_machine()):
                return
            while not self._stop.is_set():
                try:
                    self._follow()
                except BusError as exc:
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
            except RiderError as exc:  # says "cannot open the Zenoh session: ..."
                self._emit(Note(str(exc)))
                self._stop.wait(self.retry_s)
                continue
            self._opened = True
            log.info("event=ui_session_open rider=%s", self.rider.rider_id)
            return True
        return False

    def _find_machine(self) -> bool:
        while not self._stop.is_set():
            try:
                # The UI sends commands: it binds only with a command's certainty.
                self.machine_id = self.rider.pick_machine(motion=True)
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
        self._sub = self.rider.subscribe(
            WATCHED, self._enqueue, lambda alive: self._enqueue(Presence(alive))
        )
        fresh = self._refresh()
        last_status = time.monotonic() if fresh else None
        heartbeat_s = _heartbeat(fresh)
        notices = Notices(self.rider, self._emit)
        while not self._stop.is_set():
            notices.ask_overdue(time.monotonic())
            try:
                update = self._updates.get(timeout=POLL_S)
            except queue.Empty:
                continue
            notices.saw(update, time.monotonic())
            if isinstance(update, Presence):
                if not update.alive:
                    last_status = None  # a machine that comes back gets a full refresh
                self._emit(update)
                continue
            if isinstance(update, Status):
                now = time.monotonic()
                # Late past the machine's own heartbeat: it was gone (or out of reach).
                back = last_status is None or now - last_status > lost_after(heartbeat_s)
                last_status = now
                heartbeat_s = _heartbeat(update)
                # IO is published on change only: after a gap, ask for all of it again. The
                # fresh status comes last, so the page is whole when it shows the link up.
                if back and (fresh := self._refresh()):
                    heartbeat_s = _heartbeat(fresh)
                    continue
            self._emit(update)

    def _refresh(self) -> Status | None:
        """Ask for the whole picture (IO, axes, diagnostics, then status); the status if
        the machine answered with it."""
        rider = self.rider
        reads: list[Callable[[], object]] = [
            rider.io,
            rider.axes,
            rider.diag,
            rider.calibration,
            rider.status,
        ]
        status: Status | None = None
        for read in reads:
            if self._stop.is_set():
                return None
            try:
                got = read()
            except BusError:
                raise  # the session is broken: `_run` declares everything again
            except RiderError as exc:
                log.info("event=ui_refresh_failed error=%r", str(exc))
                continue
            for update in got if isinstance(got, list) else [got]:
                if isinstance(
                    update, Status | IoValue | AxisRecord | CycleDiag | CalibrationRecord
                ):
                    self._emit(update)
                    status = update if isinstance(update, Status) else status
        return status

    def _enqueue(self, update: Update) -> None:
        # Zenoh's callback thread: never block it; a full queue drops the update.
        with contextlib.suppress(queue.Full):
            self._updates.put_nowait(update)

    def _emit(self, update: Update) -> None:
        try:
            self.sink(update)
        except RuntimeError:
            self._stop.set()  # the event loop is gone: the server is shutting down

    def _undeclare(self) -> None:
        if self._sub is not None:
            self._sub.close()
            self._sub = None

    def _close(self) -> None:
        self._undeclare()
        if self._opened:
            self._opened = False
            self.rider.close()
            log.info("event=ui_session_closed")


def _heartbeat(status: Status | None) -> float:
    """The machine's status heartbeat as its status tells it (older machines: the default)."""
    return (status.heartbeat_s if status is not None else None) or DEFAULT_HEARTBEAT_S


class Notices:
    """The completion notice of every motion the bridge saw end: the one published, or, when
    none came within `NOTICE_WAIT_S` of the status that showed the motion over, asked for."""

    def __init__(self, rider: Rider, emit: Callable[[Update], None]) -> None:
        self.rider, self.emit = rider, emit
        self._moving: str | None = None
        self._seen: deque[str] = deque(maxlen=64)
        self._due: dict[str, float] = {}

    def saw(self, update: Update, now: float) -> None:
        if isinstance(update, Completion):
            self._seen.append(update.transaction_id)
            self._due.pop(update.transaction_id, None)
        elif isinstance(update, Status):
            tid = update.motion.transaction_id if update.motion is not None else None
            if self._moving is not None and tid != self._moving and self._moving not in self._seen:
                self._due[self._moving] = now + NOTICE_WAIT_S
            self._moving = tid

    def ask_overdue(self, now: float) -> None:
        for tid, due in list(self._due.items()):
            if now < due:
                continue
            del self._due[tid]
            try:
                notice = self.rider.done(tid, timeout=NOTICE_WAIT_S)
            except RiderError as exc:  # unknown to the machine, or no answer: nothing to show
                log.info("event=ui_notice_unavailable tx=%s error=%r", tid, str(exc))
                continue
            if notice is not None:
                self._seen.append(tid)
                self.emit(notice)
