"""Replies never hold the scan thread: a reply takes the asker's QoS (Zenoh 1.8 on) and may
wait on a full link, so the work the scan thread runs for a query (a diagnostics reset, a
simulator fault, a command queued before the first scan, a refused calibration) hands its reply
to the outbox's thread.

The query here is a stand-in recording what the bus asks of it (`reply`'s settings, the thread
that sent it, the end of the query), one that can be made to wait as a full link would; the
first test asks a real Zenoh session what it does with a reply's QoS. The test's own thread plays
the scan thread (`ScanLoop.service_inbox`).
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import msgpack
import pytest
import zenoh
from pydantic import BaseModel

from ride_machine.schema.codec import Format, decode
from ride_machine.schema.commands import Command, Reply
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.sim import SimWorldState
from ride_machine.service.bus.commands import Commands
from ride_machine.service.bus.injection import Injection
from ride_machine.service.bus.outbox import OUTBOX_THREAD, Outbox
from ride_machine.service.bus.request import Request, put, send
from ride_machine.service.bus.writes import Writes, on_scan_thread
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.errors import NotAvailable
from tests.rig import Rig
from tests.service.bus.test_bus_routes import WALL, Echo, FakeWorld, Host

BASE = "machine/o1"
WAIT_S = 5.0


@dataclass
class Sent:
    """One reply as the bus sent it."""

    thread: str
    key: str
    payload: bytes
    settings: dict[str, Any]


@dataclass
class Query:
    """What `send` uses of a `zenoh.Query`: `with query:` (its end) and `reply`."""

    attachment: None = None
    sent: list[Sent] = field(default_factory=list)
    gate: threading.Event | None = None
    """Set: `reply` waits for it, as Zenoh's blocking default does toward a full link."""
    replying: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)

    def __enter__(self) -> Query:
        return self

    def __exit__(self, *exc: object) -> None:
        self.done.set()

    def reply(self, key: object, payload: bytes, **settings: Any) -> None:
        self.replying.set()
        if self.gate is not None:
            assert self.gate.wait(WAIT_S), "the reply was never let through"
        self.sent.append(Sent(threading.current_thread().name, str(key), payload, settings))

    def reply_err(self, payload: bytes, **settings: Any) -> None:
        self.reply("", payload, **settings)

    def answer(self) -> Sent:
        assert self.done.wait(WAIT_S), "no reply"
        [sent] = self.sent
        return sent


def request_on(query: Query, key: str, payload: bytes = b"", fmt: Format = Format.JSON) -> Request:
    return Request(cast(zenoh.Query, query), key, payload, None, fmt, Host())


def scan(rig: Rig) -> str:
    """One turn of the scan thread's inbox, on this thread; its name."""
    rig.loop.service_inbox(rig.clock())
    return threading.current_thread().name


QOS_PROBE = """
import json, warnings, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("listen/endpoints", "[]")
conf.insert_json5("scouting/multicast/enabled", "false")
caught = []
def answer(query):
    with query:
        query.reply(query.key_expr, b"x", congestion_control=zenoh.CongestionControl.DROP)
warnings.showwarning = lambda message, category, *rest: caught.append(
    [category.__name__, str(message)]
)
warnings.simplefilter("always")
with zenoh.open(conf) as session:
    queryable = session.declare_queryable("machine/o1/qos", answer)
    replies = [r.ok is not None for r in session.get("machine/o1/qos", timeout=%r)]
    queryable.undeclare()
print(json.dumps({"replies": replies, "warnings": caught}))
"""


def test_zenoh_gives_a_reply_the_querys_qos_so_no_replier_can_make_it_drop() -> None:
    """Why the scan thread hands its replies over: since Zenoh 1.8 a reply takes the query's
    congestion control (a `get` blocks by default), and the replier's is ignored. Should this
    fail, a reply could be told to drop instead: see service/bus/outbox.py.

    In a process of its own: recording a warning raised on Zenoh's thread swaps the process's
    warning state, which no other thread of a test process may touch meanwhile."""
    done = subprocess.run(
        [sys.executable, "-c", QOS_PROBE % WAIT_S],
        capture_output=True,
        text=True,
        timeout=4 * WAIT_S,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.splitlines()[-1])
    assert seen["replies"] == [True]
    [warned] = [text for name, text in seen["warnings"] if name == "DeprecationWarning"]
    assert "congestion_control" in warned and "ignored" in warned


def test_the_bus_asks_no_qos_of_a_reply_zenoh_would_ignore_and_warn_about() -> None:
    one, several = Query(), Query()
    send(cast(zenoh.Query, one), f"{BASE}/x", Echo(key="x"), Format.JSON)
    put(cast(zenoh.Query, several), f"{BASE}/y", Echo(key="y"), Format.JSON)
    assert [set(q.sent[0].settings) for q in (one, several)] == [{"encoding"}, {"encoding"}]


@pytest.mark.hazard("H42")
def test_a_diag_reset_is_done_on_the_scan_thread_and_answered_from_the_outbox() -> None:
    rig = Rig()
    stats = CycleStats(rig.period)
    diag = stats.diag(WALL)
    writes = Writes(BASE, rig.port, stats, lambda: diag, lambda: WALL, outbox=Outbox())
    query = Query()
    writes.reset(request_on(query, f"{BASE}/diag/reset"))
    assert not query.sent  # queued for the scan thread: nothing answered yet
    scanned_on = scan(rig)
    sent = query.answer()
    assert sent.thread == OUTBOX_THREAD != scanned_on
    assert decode(CycleDiag, sent.payload, Format.JSON) == diag


def test_a_simulator_fault_under_machine_run_is_answered_from_the_outbox() -> None:
    rig, world, outbox = Rig(), FakeWorld(), Outbox()

    def run(request: Request, make: Callable[[], BaseModel]) -> None:  # as ZenohBus's
        on_scan_thread(rig.port, outbox, request, make)

    sim = Injection(BASE, world, "sim", run, lambda: WALL)
    query = Query()
    sim.inject(request_on(query, f"{BASE}/sim/estop", b'{"pressed": true}'))
    scanned_on = scan(rig)
    sent = query.answer()
    assert world.applied and sent.thread == OUTBOX_THREAD != scanned_on
    assert decode(SimWorldState, sent.payload, Format.JSON).estop_pressed


def test_a_command_queued_before_the_first_scan_is_answered_from_the_outbox() -> None:
    rig = Rig()
    rig.loop.cycle = 0  # before the first scan: the command waits for the scan thread
    commands = Commands(BASE, rig.port)
    query = Query()
    body = msgpack.packb({"transaction_id": "early-1"})
    commands.command(request_on(query, f"{BASE}/cmd/check/home", body, Format.MSGPACK))
    assert commands.deferred.drain(WAIT_S)  # its thread queued it for the scan thread
    assert len(rig.loop.inbox) == 1 and not query.sent
    scanned_on = scan(rig)
    sent = query.answer()
    assert sent.thread == OUTBOX_THREAD != scanned_on
    assert decode(Reply, sent.payload, Format.MSGPACK).transaction_id == "early-1"


def test_a_calibration_refused_on_the_scan_thread_is_answered_from_the_outbox() -> None:
    rig = Rig()
    assert rig.send(Command.CALIBRATE_TILT).success  # moving: values entered now are refused
    stats = CycleStats(rig.period)
    writes = Writes(BASE, rig.port, stats, lambda: stats.diag(WALL), lambda: WALL)
    query = Query()
    body = b'{"transaction_id": "cal-1", "rotate": {"revolution_s": 20.0, "home_arc_deg": 5.0}}'
    writes.calibration(request_on(query, f"{BASE}/calibration/set", body))
    scanned_on = scan(rig)
    sent = query.answer()
    assert sent.thread == OUTBOX_THREAD != scanned_on
    error = decode(Reply, sent.payload, Format.JSON).error
    assert error is not None and error.code is ErrorCode.WRONG_STATE


@pytest.mark.hazard("H42")
def test_a_reply_that_blocks_holds_the_outbox_never_the_scan_thread() -> None:
    rig, outbox = Rig(), Outbox()
    gate = threading.Event()
    stuck, behind = Query(gate=gate), Query()
    on_scan_thread(rig.port, outbox, request_on(stuck, f"{BASE}/a"), lambda: Echo(key="a"))
    on_scan_thread(rig.port, outbox, request_on(behind, f"{BASE}/b"), lambda: Echo(key="b"))
    scan(rig)  # returns while the first reply waits on its "full link"
    assert stuck.replying.wait(WAIT_S)
    assert not stuck.sent and not behind.sent
    gate.set()
    assert [stuck.answer().key, behind.answer().key] == [f"{BASE}/a", f"{BASE}/b"]  # in order


def test_work_that_never_runs_is_refused_from_the_outbox_not_the_stopping_thread() -> None:
    rig, outbox = Rig(), Outbox()
    query = Query()
    on_scan_thread(rig.port, outbox, request_on(query, f"{BASE}/a"), lambda: Echo(key="a"))
    rig.loop.reject_pending("machine daemon is shutting down")
    assert outbox.drain(WAIT_S)
    sent = query.answer()
    assert sent.thread == OUTBOX_THREAD
    error = decode(Reply, sent.payload, Format.JSON).error
    assert error is not None and error.code is ErrorCode.NOT_AVAILABLE


def test_a_full_outbox_drops_the_reply_and_says_so(caplog: pytest.LogCaptureFixture) -> None:
    outbox, gate = Outbox(capacity=1), threading.Event()
    outbox.later(lambda: cast(Any, gate.wait(WAIT_S)), f"{BASE}/a")
    outbox.later(lambda: pytest.fail("a dropped reply was sent"), f"{BASE}/b")
    gate.set()
    assert outbox.drain(WAIT_S)
    assert f"event=reply_dropped key={BASE}/b reason=outbox_full" in caplog.text


def test_a_refusal_raised_on_the_scan_thread_is_sent_from_the_outbox() -> None:
    rig, outbox = Rig(), Outbox()
    query = Query()

    def make() -> Echo:
        raise NotAvailable("the simulated plant: gone")

    on_scan_thread(rig.port, outbox, request_on(query, f"{BASE}/sim/estop"), make)
    scanned_on = scan(rig)
    sent = query.answer()
    assert sent.thread == OUTBOX_THREAD != scanned_on
    assert "gone" in decode(Reply, sent.payload, Format.JSON).error.message  # type: ignore[union-attr]
