"""What the machine publishes: status, IO, axes, completions, calibration, diagnostics, events.

`Publications` is the scan loop's sink (`service.core.scan.sink.LoopSink`), made before the loop it
serves and knowing nothing of it. Every publication names this session (its source info), so a
Rider drops samples of any other session that holds (or forges) this machine's keys.
Publishers drop rather than block.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import zenoh

from ride_machine.schema import keys as machine_keys
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import CalibrationRecord
from ride_machine.schema.codec import Format, encode
from ride_machine.schema.completion import Completion
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import Fault, FaultCode, MachineState, Status
from ride_machine.service.adapters.eventdb import StoredRow
from ride_machine.service.adapters.eventlog import EventLog
from ride_machine.service.adapters.eventread import row_payload
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.threads import NamedThread

MSGPACK = zenoh.Encoding(Format.MSGPACK.value)
"""Prebuilt for one-off publications (no encoding string parsed per put)."""


@dataclass(eq=False)
class Publications:
    """The machine's publishers; the loop's `LoopSink`."""

    session: zenoh.Session
    stats: CycleStats
    config: MachineConfig
    wall: Callable[[], float]
    events: EventLog | None = None

    def __post_init__(self) -> None:
        self.base = self.config.key_base
        self.zid = str(self.session.zid())
        self._data_pubs: dict[str, zenoh.Publisher] = {}
        self._source_sn = itertools.count(1)
        self._stop = threading.Event()
        self._diag_thread: threading.Thread | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._holder: zenoh.LivelinessToken | None = None
        self._last: Status | None = None
        """The status published last (the watchdog's trip is published as its successor)."""

    def declare(self, io_keys: Iterable[str]) -> list[Any]:
        """Declare the publishers (data keys up front, `io_keys` the IO points' `io/<kind>/
        <name>`: a first publication never pays for a declaration inside a scan cycle) and
        start the diag publisher; the caller undeclares."""
        s, b = self.session, self.base
        drop = zenoh.CongestionControl.DROP
        self._status_pub = s.declare_publisher(
            f"{b}/status",
            encoding=Format.MSGPACK.value,
            congestion_control=drop,
            priority=zenoh.Priority.DATA_HIGH,
            express=True,
        )
        self._diag_pub = s.declare_publisher(
            f"{b}/diag/cycle", encoding=Format.MSGPACK.value, congestion_control=drop
        )
        # Never put on: it only tells whether anybody (a Rider following, a storage) would
        # receive an event, from Zenoh's routing tables, where a put would be dropped anyway.
        self._events_pub = s.declare_publisher(f"{b}/events/*")
        if self.events is not None:
            self.events.subscribe(self._publish_events)
        for key in io_keys:
            self._publisher(f"{b}/{key}")
        for axis in ("rotate", "tilt"):
            self._publisher(f"{b}/axis/{axis}")
        self._diag_thread = NamedThread(target=self._diag_loop, name="diag", daemon=True)
        self._diag_thread.start()
        return [self._status_pub, self._diag_pub, self._events_pub]

    def undeclare(self) -> None:
        """Stop the diag publisher; drop the tokens and the data publishers."""
        self._stop.set()
        if self._diag_thread is not None:
            self._diag_thread.join(timeout=2.0)
        for token in (self._token, self._holder):
            if token is not None:
                token.undeclare()
        for pub in reversed(list(self._data_pubs.values())):
            pub.undeclare()
        self._data_pubs.clear()

    def publish_status(self, status: Status) -> None:
        self._last = status
        self._put_status(status)
        if self._token is None:
            # Alive once there is a status to answer with: a Rider that sees the token and
            # asks at once must get one (the loop publishes its records before this call).
            self._token = self.session.liveliness().declare_token(f"{self.base}/alive")

    def hold(self) -> None:
        """Declare this session the holder of the id, before any queryable: a Rider that gets
        a reply from it and asks who holds the id finds it (a restarted daemon's first reply
        came before its holder token: `DuplicateMachine` on a loaded host)."""
        key = machine_keys.holder_key(self.base, self.zid)
        self._holder = self.session.liveliness().declare_token(key)

    def _source(self) -> zenoh.SourceInfo:
        """Names this session on a publication. The sequence number only counts."""
        return zenoh.SourceInfo(self._status_pub.id, next(self._source_sn) & 0xFFFFFFFF)

    def _publisher(self, key: str) -> zenoh.Publisher:
        """The publisher of a data key (declared up front by `declare`)."""
        pub = self._data_pubs.get(key)
        if pub is None:
            pub = self.session.declare_publisher(
                key,
                encoding=Format.MSGPACK.value,
                congestion_control=zenoh.CongestionControl.DROP,
            )
            self._data_pubs[key] = pub
        return pub

    def publish_io(self, points: list[IoValue]) -> None:
        for point in points:
            self._publisher(f"{self.base}/io/{point.kind}/{point.name}").put(
                encode(point), source_info=self._source()
            )

    def publish_axes(self, records: list[AxisRecord]) -> None:
        for record in records:
            self._publisher(f"{self.base}/axis/{record.axis}").put(
                encode(record), source_info=self._source()
            )

    def _put(self, key: str, payload: bytes, **options: Any) -> None:
        """A one-off publication on `key` (no declared publisher: keys vary)."""
        self.session.put(
            key,
            payload,
            encoding=MSGPACK,
            congestion_control=zenoh.CongestionControl.DROP,
            source_info=self._source(),
            **options,
        )

    def publish_completion(self, notice: Completion) -> None:
        """A motion ended: its notice on `done/<transaction_id>` (scan thread, after the status)."""
        self._put(
            f"{self.base}/done/{notice.transaction_id}",
            encode(notice),
            priority=zenoh.Priority.DATA_HIGH,
        )

    def publish_calibration(self, record: CalibrationRecord) -> None:
        """The calibration changed (measured, entered by hand, or at start-up): scan thread."""
        self._put(f"{self.base}/calibration", encode(record))

    def publish_watchdog_trip(self, stalled_s: float) -> None:
        """From the watchdog thread: tell everyone at once, the scan thread may be stuck."""
        last = self._last
        if last is None:
            return
        message = (
            f"scan loop stalled for {stalled_s * 1000:.0f} ms; outputs forced safe by the watchdog"
        )
        fault = Fault(code=FaultCode.WATCHDOG, message=message)
        self._put_status(faulted(last, fault, self.wall()))

    def _put_status(self, status: Status) -> None:
        # The source names this session: a Rider drops statuses of another holder of the id.
        self._status_pub.put(
            encode(status), source_info=zenoh.SourceInfo(self._status_pub.id, status.seq)
        )

    def diag(self) -> CycleDiag:
        diag = self.stats.diag(self.wall())
        if self.events is None:
            return diag
        return diag.model_copy(update={"events": self.events.diag()})

    def _diag_loop(self) -> None:
        """The loop's diagnostics every `diag_period_s`, made only while a subscriber matches
        `diag` (a `diag` get makes its own): an idle daemon with nobody watching spent 0.65 ms
        a second on them, a twentieth of its CPU (BENCHMARKS.md, section 5)."""
        period = self.config.bus.diag_period_s
        while not self._stop.wait(period):
            if subscribed(self._diag_pub):
                self._diag_pub.put(encode(self.diag()), source_info=self._source())

    def _publish_events(self, rows: list[StoredRow]) -> None:
        """From the event log's writer thread: each event on its own key, `events/<seq>`, so a
        Zenoh storage keeps them all (it keeps the latest sample per key). Not made at all
        while no subscriber matches `events/*`: under a command stream with nobody following,
        making and putting them was a third of the writer's work per command (BENCHMARKS.md,
        section 1); a subscriber declared later would not have received them either."""
        if self._stop.is_set() or not subscribed(self._events_pub):
            return
        for row in rows:
            self._put(f"{self.base}/events/{row[0]}", row_payload(row))


def subscribed(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches `publisher`'s key expression (zenoh-python 1.x returns a
    `MatchingStatus`, which its type stubs call a bool)."""
    status: Any = publisher.matching_status
    return bool(getattr(status, "matching", status))


def faulted(last: Status, fault: Fault, now: float, **also: object) -> Status:
    """The status that follows `last` once `fault` has put the machine in FAULT_HW (the
    watchdog's trip here, a dead daemon in the supervisor's bus); `also`: other fields."""
    update = {"state": MachineState.FAULT_HW, "previous_state": last.state, "fault": fault}
    return last.model_copy(update={**update, "seq": last.seq + 1, "time": now, **also})
