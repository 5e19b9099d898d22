"""The machine's Zenoh adapter; this package (with `bus.supervisor`) alone imports `zenoh`.

Queryables decode requests on Zenoh's callback thread. A command runs right there, between two
scan cycles, under the loop's lock (one writer at a time; the next cycle still reads inputs and
handles E-stop before any output changes) and is answered from the same thread: no hand-off.
Other work for the machine goes to the scan thread through the `Inbox`.
Read-only queries (status, IO, axes, diagnostics) are answered from the latest published
records without touching state. Publishers drop rather than block under congestion.
"""

from __future__ import annotations

import itertools
import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import zenoh
from pydantic import BaseModel

from hal.sim import SimHal
from schema import keys as machine_keys
from schema import rider as rider_keys
from schema.axes import AxisRecord
from schema.calibration import CalibrationRecord, CalibrationSet
from schema.codec import (
    MAX_PAYLOAD_BYTES,
    DecodeError,
    Format,
    decode_raw,
    encode,
    sniff_format,
    validate,
)
from schema.commands import REQUEST_MODELS, Command, Reply, transaction_id_of
from schema.completion import Completion
from schema.credentials import MACHINE, zenoh_settings
from schema.diag import CycleDiag
from schema.errors import Error, ErrorCode
from schema.events import (
    Event,
    EventPage,
    EventQuery,
    ParamEvent,
    QueryError,
    RiderEvent,
    selector_params,
)
from schema.findings import Findings
from schema.io import IoValue
from schema.params import ParamSet, ParamValue
from schema.status import Fault, FaultCode, MachineState, Status
from service import simfaults
from service.config import MachineConfig
from service.errors import MachineError
from service.eventlog import EventLog
from service.loop import LoopCall, PendingCommand, ScanLoop, calibration_record
from service.persist import SaveTicket
from service.timing import CycleStats

log = logging.getLogger(__name__)

WILDCARD_CHARS = ("*", "$")
SAVE_WAIT_S = 5.0
"""How long a manual calibration write may take before its reply says it was not saved."""
MAX_RIDERS = 1024
"""Riders whose heartbeat the bus keeps track of at once."""
LOCK_TIMEOUT_S = 0.5
"""How long a command waits for the scan thread to finish a cycle before BUSY (a stalled loop)."""
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
"""Without --listen or a config file: this host only (beyond it, use an authenticated profile)."""


ENCODINGS = {fmt: zenoh.Encoding(fmt.value) for fmt in Format}
"""Prebuilt, so a reply does not parse its encoding string."""


class ParamService(Protocol):
    """What the bus needs from the parameter registry (service/params.py)."""

    def list(self) -> list[ParamValue]: ...

    def get(self, name: str) -> ParamValue: ...

    def set(self, name: str, req: ParamSet, *, moving: bool, now: float) -> ParamValue: ...


class ConfigChecker(Protocol):
    """Validates the running config, or a candidate one sent as a TOML/JSON payload."""

    def __call__(self, candidate: bytes | None) -> Findings: ...


def reply_format(query: zenoh.Query, payload: bytes | None = None) -> Format:
    """JSON when asked (`?format=json`, a JSON encoding, or JSON text sent); msgpack otherwise."""
    fmt = query.parameters.get("format")
    if fmt is not None:
        return Format.JSON if fmt.lower() == "json" else Format.MSGPACK
    encoding = str(query.encoding) if query.encoding is not None else None
    if payload:
        return sniff_format(payload, encoding)
    return Format.JSON if encoding and encoding.startswith(Format.JSON) else Format.MSGPACK


def _payload(query: zenoh.Query) -> bytes:
    return query.payload.to_bytes() if query.payload is not None else b""


def _encoding(query: zenoh.Query) -> str | None:
    return str(query.encoding) if query.encoding is not None else None


class ZenohBus:
    """Puts one machine on Zenoh under `<key_prefix>/<id>`; implements the loop's `LoopSink`."""

    def __init__(
        self,
        session: zenoh.Session,
        loop: ScanLoop,
        stats: CycleStats,
        config: MachineConfig,
        *,
        sim: SimHal | None = None,
        params: ParamService | None = None,
        check_config: ConfigChecker | None = None,
        wall: Callable[[], float] = time.time,
        clock: Callable[[], float] = time.monotonic,
        events: EventLog | None = None,
        sim_elsewhere: bool = False,
    ) -> None:
        """`sim_elsewhere`: another session (the supervisor) answers `sim/**` for this machine."""
        self.session = session
        self.sim_elsewhere = sim_elsewhere
        self.loop = loop
        self.stats = stats
        self.config = config
        self.sim = sim
        self.params = params
        self.check_config = check_config
        self.events = events
        self.wall = wall
        self.clock = clock
        """The scan loop's clock (the runner's), for commands run between cycles."""
        self.base = config.key_base
        self._declared: list[Any] = []
        self._data_pubs: dict[str, zenoh.Publisher] = {}
        self._stop = threading.Event()
        self._source_sn = itertools.count(1)
        self._diag_thread: threading.Thread | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._holder: zenoh.LivelinessToken | None = None
        self.zid = str(session.zid())
        self.others: set[str] = set()
        """Other sessions that hold this machine's id (its `holder/<zid>` token): duplicates."""
        self.riders_alive: set[str] = set()
        self._beats: dict[str, float] = {}
        self._commands = {
            f"{self.base}/cmd/{c.key}": (c, zenoh.KeyExpr(f"{self.base}/cmd/{c.key}"))
            for c in Command
        }
        """Exact command key → (command, its prebuilt key expression: no parsing per reply)."""

    # ---------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Declare queryables and publishers, start the diag publisher; the liveliness token
        follows with the first status (`publish_status`)."""
        s, b = self.session, self.base
        # One queryable for every command key: a query reaches one callback, where a queryable
        # per command beside a `cmd/**` one made every command wait for two (bench/roundtrip).
        self._declared.append(s.declare_queryable(f"{b}/cmd/**", self._on_cmd))
        self._declared.append(s.declare_queryable(f"{b}/status", self._on_status))
        self._declared.append(s.declare_queryable(f"{b}/io/**", self._on_io))
        self._declared.append(s.declare_queryable(f"{b}/axis/**", self._on_axis))
        self._declared.append(s.declare_queryable(f"{b}/diag/cycle", self._on_diag))
        self._declared.append(s.declare_queryable(f"{b}/diag/reset", self._on_diag_reset))
        self._declared.append(s.declare_queryable(f"{b}/config/validate", self._on_validate))
        self._declared.append(s.declare_queryable(f"{b}/done/**", self._on_done))
        self.loop.completion_listeners.append(self.publish_completion)
        self._declared.append(s.declare_queryable(f"{b}/calibration", self._on_calibration))
        self._declared.append(s.declare_queryable(f"{b}/calibration/set", self._on_calibration_set))
        self.loop.calibration_listeners.append(self.publish_calibration)
        if self.params is not None:
            self._declared.append(s.declare_queryable(f"{b}/params/**", self._on_params))
        # Declared without a simulator too: `sim/*` on real hardware answers NOT_AVAILABLE
        # at once instead of leaving the caller to time out (a supervisor answers for its child).
        if self.sim is not None or not self.sim_elsewhere:
            self._declared.append(s.declare_queryable(f"{b}/sim/**", self._on_sim))
        if self.events is not None:
            self._declared.append(s.declare_queryable(f"{b}/events", self._on_events))
            self.events.subscribe(self._publish_events)
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
        self._declared += [self._status_pub, self._diag_pub]
        for point in self.loop.points.all():
            self._publisher(f"{b}/io/{point.kind}/{point.name}")
        for axis in ("rotate", "tilt"):
            self._publisher(f"{b}/axis/{axis}")
        self._declared.append(
            s.liveliness().declare_subscriber(rider_keys.ALIVE_KEYS, self._on_rider, history=True)
        )
        self._declared.append(s.declare_subscriber(rider_keys.HEARTBEAT_KEYS, self._on_heartbeat))
        # Before our own token: any other holder of this id is a duplicate, now or later.
        self._declared.append(
            s.liveliness().declare_subscriber(f"{b}/holder/*", self._on_holder, history=True)
        )
        self.loop.beats = self
        self._diag_thread = threading.Thread(target=self._diag_loop, name="diag", daemon=True)
        self._diag_thread.start()
        log.info("event=bus_started base=%s zid=%s", b, s.zid())

    def close(self) -> None:
        """Undeclare everything (the session itself is closed by its owner)."""
        self._stop.set()
        if self._diag_thread is not None:
            self._diag_thread.join(timeout=2.0)
        for token in (self._token, self._holder):
            if token is not None:
                token.undeclare()
        for entity in reversed(self._declared + list(self._data_pubs.values())):
            entity.undeclare()
        self._declared.clear()
        self._data_pubs.clear()

    # ----------------------------------------------------------------------- publications
    def publish_status(self, status: Status) -> None:
        # The source names this session: a Rider drops statuses of another holder of the id.
        self._status_pub.put(
            encode(status), source_info=zenoh.SourceInfo(self._status_pub.id, status.seq)
        )
        if self._token is None:
            # Alive once there is a status to answer with: a Rider that sees the token and
            # asks at once must get one (the loop sets `published.status` before this call).
            live = self.session.liveliness()
            self._holder = live.declare_token(machine_keys.holder_key(self.base, self.zid))
            self._token = live.declare_token(f"{self.base}/alive")

    def _source(self) -> zenoh.SourceInfo:
        """Names this session on a publication: a Rider drops samples of any other session
        that holds (or forges) this machine's keys. The sequence number only counts."""
        return zenoh.SourceInfo(self._status_pub.id, next(self._source_sn) & 0xFFFFFFFF)

    def _publisher(self, key: str) -> zenoh.Publisher:
        """The publisher of a data key; declared up front in `start()`, so a first
        publication never pays for a declaration inside a scan cycle."""
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

    def publish_completion(self, notice: Completion) -> None:
        """A motion ended: its notice on `done/<transaction_id>` (scan thread, after the status)."""
        self.session.put(
            f"{self.base}/done/{notice.transaction_id}",
            encode(notice),
            encoding=Format.MSGPACK.value,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_HIGH,
            source_info=self._source(),
        )

    def publish_calibration(self, record: CalibrationRecord) -> None:
        """The calibration changed (measured, entered by hand, or at start-up): scan thread."""
        self.session.put(
            f"{self.base}/calibration",
            encode(record),
            encoding=Format.MSGPACK.value,
            congestion_control=zenoh.CongestionControl.DROP,
            source_info=self._source(),
        )

    def publish_watchdog_trip(self, stalled_s: float) -> None:
        """From the watchdog thread: tell everyone at once, the scan thread may be stuck."""
        last = self.loop.published.status
        if last is None:
            return
        status = last.model_copy(
            update={
                "state": MachineState.FAULT_HW,
                "previous_state": last.state,
                "fault": Fault(
                    code=FaultCode.WATCHDOG,
                    message=f"scan loop stalled for {stalled_s * 1000:.0f} ms;"
                    " outputs forced safe by the watchdog",
                ),
                "seq": last.seq + 1,
                "time": self.wall(),
            }
        )
        self._status_pub.put(
            encode(status), source_info=zenoh.SourceInfo(self._status_pub.id, status.seq)
        )

    def _diag(self) -> CycleDiag:
        diag = self.stats.diag(self.wall())
        if self.events is None:
            return diag
        return diag.model_copy(update={"events": self.events.diag()})

    def _diag_loop(self) -> None:
        period = self.config.bus.diag_period_s
        while not self._stop.wait(period):
            self._diag_pub.put(encode(self._diag()), source_info=self._source())

    def _publish_events(self, events: list[Event]) -> None:
        """From the event log's writer thread: each event on its own key, `events/<seq>`, so a
        Zenoh storage keeps them all (it keeps the latest sample per key)."""
        if self._stop.is_set():
            return
        for event in events:
            self.session.put(
                f"{self.base}/events/{event.seq}",
                encode(event),
                encoding=Format.MSGPACK.value,
                congestion_control=zenoh.CongestionControl.DROP,
                source_info=self._source(),
            )

    # --------------------------------------------------------------------------- commands
    def _on_cmd(self, query: zenoh.Query) -> None:
        """Every `cmd/...` query: a known command key runs it; anything else is refused."""
        target = self._commands.get(str(query.key_expr))
        if target is None:
            self._on_cmd_other(query)
            return
        self._on_command(target[0], target[1], query)

    def _on_command(self, command: Command, key_expr: zenoh.KeyExpr, query: zenoh.Query) -> None:
        key = str(key_expr)
        data = _payload(query)
        fmt = reply_format(query, data)
        raw: Any = None
        try:
            raw = decode_raw(data, sniff_format(data, _encoding(query))) if data else None
            if raw is None:
                raise DecodeError(
                    Error(
                        code=ErrorCode.BAD_PAYLOAD,
                        message="a command needs a payload with at least a transaction_id,"
                        ' e.g. {"transaction_id": "t1"}',
                        path="/transaction_id",
                    )
                )
            request = validate(REQUEST_MODELS[command], raw)
        except DecodeError as exc:
            self._reply_now(query, key, fmt, exc.error, command, transaction_id_of(raw))
            return

        def respond(reply: Reply) -> None:
            with query:
                query.reply(key_expr, encode(reply, fmt), encoding=ENCODINGS[fmt])

        sender = _sender(query)
        reply = self.loop.execute_between_cycles(
            command, request, self.clock, sender=sender, timeout=LOCK_TIMEOUT_S
        )
        if reply is not None:
            respond(reply)
            return
        # Before the first scan (no input image yet) or after shutdown: the scan thread decides.
        if not self.loop.inbox.put(PendingCommand(command, request, respond, sender)):
            self._reply_now(
                query,
                key,
                fmt,
                Error(code=ErrorCode.BUSY, message="command queue full; retry later"),
                command,
                request.transaction_id,
            )

    def _on_cmd_other(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        prefix = f"{self.base}/cmd/"
        suffix = key[len(prefix) :] if key.startswith(prefix) else key
        fmt = reply_format(query, _payload(query))
        if any(c in key for c in WILDCARD_CHARS):
            error = Error(
                code=ErrorCode.BAD_KEY,
                message=f"wildcards are not allowed in a command key: {key!r}; name one command"
                f" of one machine, e.g. {prefix}home",
            )
            with query:
                query.reply_err(encode(_failure(error, None, self.wall()), fmt), encoding=fmt.value)
            return
        known = ", ".join(c.key for c in Command)
        error = Error(
            code=ErrorCode.UNKNOWN_COMMAND,
            message=f"unknown command {suffix!r}; known: {known}",
        )
        self._reply_now(query, key, fmt, error, None, transaction_id_of(_try_raw(query)))

    def _refuse_wildcard(
        self, query: zenoh.Query, key: str, fmt: Format, what: str, example: str
    ) -> None:
        error = Error(
            code=ErrorCode.BAD_KEY,
            message=f"wildcards are not allowed in {what}: {key!r}; name one key of one machine,"
            f" e.g. {self.base}/{example}",
        )
        self._reply_now(query, key, fmt, error, None, transaction_id_of(_try_raw(query)))

    def _reply_now(
        self,
        query: zenoh.Query,
        key: str,
        fmt: Format,
        error: Error,
        command: Command | None,
        transaction_id: str | None,
    ) -> None:
        reply = Reply.failure(
            error,
            transaction_id=transaction_id,
            command=command.value if command else None,
            timecode=self.wall(),
            state=self.loop.published.status.state if self.loop.published.status else None,
        )
        with query:
            query.reply(key, encode(reply, fmt), encoding=fmt.value)

    # ------------------------------------------------------------------------- read-only
    def _on_status(self, query: zenoh.Query) -> None:
        with query:
            status = self.loop.published.status
            if status is not None:
                fmt = reply_format(query)
                query.reply(f"{self.base}/status", encode(status, fmt), encoding=fmt.value)

    def _on_io(self, query: zenoh.Query) -> None:
        points = self.loop.published.io.values()
        self._reply_matching(query, [(f"io/{p.kind}/{p.name}", p) for p in points])

    def _on_axis(self, query: zenoh.Query) -> None:
        records = self.loop.published.axes.values()
        self._reply_matching(query, [(f"axis/{r.axis}", r) for r in records])

    def _reply_matching(self, query: zenoh.Query, items: list[tuple[str, BaseModel]]) -> None:
        """One reply per record whose key the (possibly wildcard) query selects."""
        with query:
            fmt = reply_format(query)
            for suffix, record in items:
                key = f"{self.base}/{suffix}"
                if query.key_expr.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, encode(record, fmt), encoding=fmt.value)

    def _on_done(self, query: zenoh.Query) -> None:
        """How a motion ended: its notice, IN_PROGRESS while it runs, or UNKNOWN_TRANSACTION;
        a wildcard (`done/**`) gets every notice the machine remembers."""
        key = str(query.key_expr)
        prefix = f"{self.base}/done/"
        log_ = self.loop.completions
        if any(c in key for c in WILDCARD_CHARS):
            self._reply_matching(query, [(f"done/{n.transaction_id}", n) for n in log_.recent()])
            return
        tid = key[len(prefix) :]
        fmt = reply_format(query)
        found = log_.lookup(tid)
        if isinstance(found, Completion):
            with query:
                query.reply(key, encode(found, fmt), encoding=fmt.value)
            return
        if found is not None:
            error = Error(
                code=ErrorCode.IN_PROGRESS,
                message=f"{found.command} {tid} has not ended yet; its notice will be"
                f" published on {key}",
            )
        else:
            error = Error(
                code=ErrorCode.UNKNOWN_TRANSACTION,
                message=f"no motion {tid!r} is known here (never accepted, forgotten, or"
                " before this daemon started)",
                path="/transaction_id",
            )
        self._reply_now(query, key, fmt, error, None, tid)

    def _on_calibration(self, query: zenoh.Query) -> None:
        with query:
            record = self.loop.published.calibration
            if record is not None:
                fmt = reply_format(query)
                query.reply(f"{self.base}/calibration", encode(record, fmt), encoding=fmt.value)

    def _on_calibration_set(self, query: zenoh.Query) -> None:
        """Values entered by hand: applied on the scan thread, answered once they are saved."""
        key = f"{self.base}/calibration/set"
        asked = str(query.key_expr)
        data = _payload(query)
        fmt = reply_format(query, data)
        if asked != key:
            if asked.endswith("/calibration/set"):
                self._refuse_wildcard(query, asked, fmt, "a calibration write", "calibration/set")
            else:
                query.drop()  # a wildcard read that only happens to cover it
            return
        try:
            if not data:
                raise DecodeError(
                    Error(
                        code=ErrorCode.BAD_PAYLOAD,
                        message='send {"transaction_id": "…", "tilt": {"offset_counts": …,'
                        ' "gain_counts_per_deg": …}} and/or "rotate": {"revolution_s": …,'
                        ' "home_arc_deg": …}',
                        path="/transaction_id",
                    )
                )
            req = validate(CalibrationSet, decode_raw(data, sniff_format(data, _encoding(query))))
        except DecodeError as exc:
            self._reply_now(query, key, fmt, exc.error, None, transaction_id_of(exc.raw))
            return

        def enter(loop: ScanLoop, now: float) -> None:
            try:
                ticket = loop.control.enter_calibration(req, now)
            except MachineError as exc:
                self._reply_now(query, key, fmt, exc.to_error(), None, req.transaction_id)
                return
            record = calibration_record(loop.control.calibration, self.config.machine.id, now)
            record = record.model_copy(update={"time": self.wall()})
            log.info(
                "event=calibration_entered tx=%s timecode=%s tilt=%s rotate=%s",
                req.transaction_id,
                req.timecode,
                req.tilt is not None,
                req.rotate is not None,
            )
            # The scan thread never waits for the disk: a short-lived thread answers.
            threading.Thread(
                target=self._answer_saved,
                args=(query, key, fmt, req.transaction_id, record, ticket),
                name="calibration-saved",
                daemon=True,
            ).start()

        self._to_loop(query, key, fmt, enter)

    def _answer_saved(
        self,
        query: zenoh.Query,
        key: str,
        fmt: Format,
        tid: str,
        record: CalibrationRecord,
        ticket: SaveTicket | None,
    ) -> None:
        problem = None
        if ticket is not None:
            problem = ticket.problem if ticket.wait(SAVE_WAIT_S) else "the write did not finish"
        if problem is not None:
            error = Error(
                code=ErrorCode.STORAGE_FAILED,
                message=f"calibration entered and in use now, but NOT saved: {problem}",
            )
            self._reply_now(query, key, fmt, error, None, tid)
            return
        with query:
            query.reply(key, encode(record, fmt), encoding=fmt.value)

    def _on_diag(self, query: zenoh.Query) -> None:
        fmt = reply_format(query)
        key = f"{self.base}/diag/cycle"
        if "reset" in query.parameters:
            # The old spelling of a reset: a write hidden in a parameter, which no ACL can see.
            error = Error(
                code=ErrorCode.BAD_KEY,
                message=f"diag/cycle is read-only; reset the counters with a query on"
                f" {self.base}/diag/reset",
            )
            self._reply_now(query, key, fmt, error, None, None)
            return
        with query:
            query.reply(key, encode(self._diag(), fmt), encoding=fmt.value)

    def _on_diag_reset(self, query: zenoh.Query) -> None:
        """Reply with the counters as they were, then reset them, on the scan thread."""
        key = f"{self.base}/diag/reset"
        asked = str(query.key_expr)
        fmt = reply_format(query)
        if asked != key:
            if asked.endswith("/diag/reset"):
                # `machine/*/diag/reset` would reset every machine's counters at once.
                self._refuse_wildcard(query, asked, fmt, "a diagnostics reset", "diag/reset")
            else:
                query.drop()  # a wildcard read (e.g. `diag/**`) that only happens to cover it
            return

        def reset(loop: ScanLoop, now: float) -> None:
            with query:
                query.reply(key, encode(self._diag(), fmt), encoding=fmt.value)
            self.stats.reset(self.wall())

        self._to_loop(query, key, fmt, reset)

    def _on_validate(self, query: zenoh.Query) -> None:
        key = f"{self.base}/config/validate"
        data = _payload(query)
        fmt = reply_format(query)
        if data.lstrip()[:1] == b"{" and query.parameters.get("format") is None:
            fmt = Format.JSON  # a JSON candidate is answered in JSON (TOML keeps the default)
        if self.check_config is None:
            error = Error(code=ErrorCode.NOT_AVAILABLE, message="no config checker")
            self._reply_now(query, key, fmt, error, None, None)
            return
        if len(data) > MAX_PAYLOAD_BYTES:
            # Parsing runs on Zenoh's thread and holds the GIL: a few MiB stall the scan loop.
            error = Error(
                code=ErrorCode.PAYLOAD_TOO_LARGE,
                message=f"candidate config is {len(data)} bytes, the limit is {MAX_PAYLOAD_BYTES}",
            )
            self._reply_now(query, key, fmt, error, None, None)
            return
        with query:
            findings = self.check_config(data or None)
            query.reply(key, encode(findings, fmt), encoding=fmt.value)

    # ------------------------------------------------------------------------- parameters
    def _on_params(self, query: zenoh.Query) -> None:
        params = self.params
        assert params is not None
        key = str(query.key_expr)
        name = key[len(f"{self.base}/params/") :]
        data = _payload(query)
        fmt = reply_format(query, data)
        wild = any(c in key for c in WILDCARD_CHARS)
        if wild and data:
            # A write must name one parameter of one machine: `machine/*/params/x` reaches all.
            self._refuse_wildcard(query, key, fmt, "a parameter write", "params/<name>")
            return
        # Reads never touch the scan thread: the registry hands out immutable values.
        if wild:
            self._reply_matching(query, [(f"params/{p.name}", p) for p in params.list()])
            return
        if not data:
            try:
                value = params.get(name)
            except MachineError as exc:
                self._reply_now(query, key, fmt, exc.to_error(), None, None)
                return
            with query:
                query.reply(key, encode(value, fmt), encoding=fmt.value)
            return
        try:
            req = validate(ParamSet, decode_raw(data, sniff_format(data, _encoding(query))))
        except DecodeError as exc:
            self._reply_now(query, key, fmt, exc.error, None, transaction_id_of(exc.raw))
            return
        # The registry is thread-safe and its write (with fsync) stays off the scan thread;
        # the loop picks the new config up at the next cycle boundary.
        try:
            old = params.get(name).value
            value = params.set(name, req, moving=self.loop.control.is_moving(), now=self.wall())
        except MachineError as exc:
            self._reply_now(query, key, fmt, exc.to_error(), None, req.transaction_id)
            return
        if self.events is not None:
            self.events.emit_now(
                ParamEvent(
                    name=value.name,
                    old=old,
                    new=value.value,
                    persisted=value.persisted,
                    reset=req.reset,
                    transaction_id=req.transaction_id,
                )
            )
        with query:
            query.reply(key, encode(value, fmt), encoding=fmt.value)

    # --------------------------------------------------------------------------- events
    def _on_events(self, query: zenoh.Query) -> None:
        """A page of the history (`?since=&until=&since_time=&until_time=&kind=&limit=&last=`),
        read on the event log's reader thread."""
        events = self.events
        assert events is not None
        key = f"{self.base}/events"
        fmt = reply_format(query)
        if selector_params(str(query.parameters)).get("format", "").lower() == "json":
            fmt = Format.JSON  # `?last=5&format=json`: `&` separates here too
        try:
            q = EventQuery.from_text(str(query.parameters))
        except QueryError as exc:
            error = Error(code=ErrorCode.BAD_PAYLOAD, message=str(exc), path=f"?{exc.param}")
            self._reply_now(query, key, fmt, error, None, None)
            return

        def respond(page: EventPage) -> None:
            with query:
                query.reply(key, encode(page, fmt), encoding=fmt.value)

        def fail(message: str) -> None:
            error = Error(code=ErrorCode.STORAGE_FAILED, message=message)
            self._reply_now(query, key, fmt, error, None, None)

        if not events.read(q, respond, fail):
            fail_busy = Error(code=ErrorCode.BUSY, message="event reader busy; retry later")
            self._reply_now(query, key, fmt, fail_busy, None, None)

    # ------------------------------------------------------------------------------ sim
    def _on_sim(self, query: zenoh.Query) -> None:
        sim = self.sim
        key = str(query.key_expr)
        what = key[len(f"{self.base}/sim/") :]
        data = _payload(query)
        fmt = reply_format(query, data)
        if any(c in key for c in WILDCARD_CHARS):
            # Injection acts on the machine: `machine/*/sim/estop` must not press every E-stop.
            self._refuse_wildcard(query, key, fmt, "a simulator key", "sim/<fault>")
            return
        if sim is None:
            backend = self.config.hal.backend
            error = Error(
                code=ErrorCode.NOT_AVAILABLE,
                message=f"sim/{what}: this machine runs the {backend} HAL, not the simulator",
            )
            self._reply_now(query, key, fmt, error, None, transaction_id_of(_try_raw(query)))
            return
        if what == simfaults.WORLD:
            with query:
                query.reply(
                    key, encode(simfaults.world_state(sim, self.wall()), fmt), encoding=fmt.value
                )
            return
        try:
            req = simfaults.decode_request(what, data, _encoding(query))
        except DecodeError as exc:
            self._reply_now(query, key, fmt, exc.error, None, transaction_id_of(exc.raw))
            return

        def inject(loop: ScanLoop, now: float) -> None:
            simfaults.apply_fault(sim, req)
            with query:
                query.reply(
                    key, encode(simfaults.world_state(sim, self.wall()), fmt), encoding=fmt.value
                )

        self._to_loop(query, key, fmt, inject)

    # ------------------------------------------------------------------------- duplicates
    def _on_holder(self, sample: zenoh.Sample) -> None:
        """Another session declared (or dropped) this machine's id: both stop and refuse
        motion until one of them is alone again; each judges for itself, so both do."""
        zid = str(sample.key_expr).rsplit("/", 1)[-1]
        if zid == self.zid:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.others.add(zid)
            log.error("event=duplicate_id id=%s other_session=%s", self.config.machine.id, zid)
        else:
            self.others.discard(zid)
            log.warning("event=duplicate_gone id=%s other_session=%s", self.config.machine.id, zid)
        others = tuple(sorted(self.others))

        def update(loop: ScanLoop, now: float) -> None:
            loop.control.duplicate_id(others, self.zid, now)

        self.loop.inbox.put(LoopCall(update))

    # ---------------------------------------------------------------------------- riders
    def _on_heartbeat(self, sample: zenoh.Sample) -> None:
        """Only the arrival time is kept (one dict write): the scan loop judges it."""
        rider = rider_keys.rider_of(str(sample.key_expr))
        # Bounded: a flood of made-up Rider ids cannot grow this without end.
        if rider is not None and (rider in self._beats or len(self._beats) < MAX_RIDERS):
            self._beats[rider] = self.clock()

    def last_heartbeat(self, rider: str) -> float | None:
        """`RiderBeats` for the scan loop: when `rider`'s heartbeat last arrived."""
        return self._beats.get(rider)

    def _on_rider(self, sample: zenoh.Sample) -> None:
        rider = rider_keys.rider_of(str(sample.key_expr))
        if rider is None:
            return  # a Rider's id is its session id (hex): anything else is not a Rider's token
        alive = sample.kind == zenoh.SampleKind.PUT
        if alive:
            self.riders_alive.add(rider)
        else:
            self.riders_alive.discard(rider)
            self._beats.pop(rider, None)

        def update(loop: ScanLoop, now: float) -> None:
            control = loop.control
            if control.controller_rider != rider:
                return
            policy = self.config.rider_loss.policy
            acted = False
            if alive:
                control.rider_back()
            elif acted := control.rider_lost(now):
                log.warning("event=rider_lost rider=%s policy=%s", rider, policy)
            if self.events is not None:
                kind = "rider_returned" if alive else "rider_lost"
                self.events.emit(
                    RiderEvent(kind=kind, rider=rider, policy=str(policy), acted=acted),
                    now + loop.wall_offset,
                    loop.cycle,
                )

        self.loop.inbox.put(LoopCall(update))

    # ------------------------------------------------------------------------------ help
    def _to_loop(
        self,
        query: zenoh.Query,
        key: str,
        fmt: Format,
        fn: Callable[[ScanLoop, float], None],
    ) -> None:
        def rejected(error: Error) -> None:
            self._reply_now(query, key, fmt, error, None, None)

        if not self.loop.inbox.put(LoopCall(fn, rejected)):
            rejected(Error(code=ErrorCode.BUSY, message="command queue full; retry later"))


def _failure(error: Error, transaction_id: str | None, stamp: float) -> Reply:
    return Reply.failure(error, transaction_id=transaction_id, command=None, timecode=stamp)


def _sender(query: zenoh.Query) -> str | None:
    """The Rider's session id from the query's attachment (`rider=<zid>`), if it sent one."""
    if query.attachment is None:
        return None
    text = query.attachment.to_bytes()[:128].decode(errors="replace")
    name, _, value = text.partition("=")
    return value[:64] if name == "rider" and value.isalnum() else None


def _try_raw(query: zenoh.Query) -> Any:
    data = _payload(query)
    try:
        return decode_raw(data, sniff_format(data, _encoding(query))) if data else None
    except DecodeError:
        return None


ID_PROBE_S = 1.0
"""Bound of the start-up liveliness query for this machine's id. It returns as soon as every
connected peer has answered (no wait at all for a lone daemon); the bound only matters on a
slow link."""


def holders_of(session: zenoh.Session, base: str, timeout: float = ID_PROBE_S) -> list[str]:
    """The other sessions that hold `base` now (`?` for one that holds `alive` but names no
    holder: an older daemon). Asked before this daemon declares its own tokens."""
    own = str(session.zid())
    found: set[str] = set()
    alive = False
    for reply in session.liveliness().get(f"{base}/**", timeout=timeout):
        if reply.ok is None:
            continue
        rest = str(reply.ok.key_expr)[len(base) + 1 :]
        if rest == "alive":
            alive = True
        elif rest.startswith("holder/"):
            found.add(rest[len("holder/") :])
    found.discard(own)
    if alive and not found:
        found.add("?")
    return sorted(found)


def file_config(path: Path | None) -> zenoh.Config:
    """The zenoh.json5 at `path` as it is, or Zenoh's defaults without one."""
    return zenoh.Config.from_file(str(path)) if path is not None else zenoh.Config()


def zenoh_config(
    path: Path | None, listen: list[str] | None = None, connect: list[str] | None = None
) -> zenoh.Config:
    """The session config: the shared zenoh.json5 (or Zenoh's defaults), endpoints replaced."""
    conf = file_config(path)
    if path is None:
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([DEFAULT_LISTEN]))
        # As zenoh.json5: explicit endpoints only. Zenoh's own default (multicast scouting on)
        # would join any peer on the LAN, and another machine with this id would refuse us.
        conf.insert_json5("scouting/multicast/enabled", "false")
        # Read-only, as in zenoh.json5: Riders' default-machine lookup reads our tokens there.
        conf.insert_json5("adminspace", "{enabled: true, permissions: {read: true, write: false}}")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    # Secrets come from files named in the environment, never from the image or this file.
    for setting, value in zenoh_settings(MACHINE).items():
        conf.insert_json5(setting, value)
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    return zenoh.open(conf)


def close_session(session: zenoh.Session, timeout: float = 3.0) -> bool:
    """Close off the calling thread with a bound: a lossy link can make close() hang."""
    done = threading.Event()

    def closer() -> None:
        session.close()
        done.set()

    threading.Thread(target=closer, name="zenoh-close", daemon=True).start()
    return done.wait(timeout)
