"""`cmd/**` on Zenoh's own thread: a command runs there when the loop's lock is free, and waits
on `Deferred`'s thread, in arrival order, when it is not (mid-cycle, or a stalled loop).

A real Zenoh session queries its own queryables; the machine is the simulator rig with a fake
clock, and the test holds the loop's lock where the scan thread would.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator

import msgpack
import pytest
import zenoh

from ride_machine.schema.codec import Format, decode
from ride_machine.schema.commands import Reply
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import CommandEvent
from ride_machine.service.bus import commands
from ride_machine.service.bus.commands import Commands, Deferred
from ride_machine.service.bus.routes import declare
from ride_machine.service.core.history.events import ListEventSink
from ride_machine.service.core.scan.port import LoopPort
from tests.rig import Rig
from tests.service.bus.test_bus_routes import Host

BASE = "machine/c1"
_ids = itertools.count()


@pytest.fixture
def machine(session: zenoh.Session) -> Iterator[tuple[Rig, Commands, ListEventSink]]:
    sink = ListEventSink()
    rig = Rig(events=sink)
    bus = Commands(BASE, LoopPort(rig.loop, rig.clock))
    declared = declare(session, BASE, Host(), bus.routes())
    yield rig, bus, sink
    for entity in declared:
        entity.undeclare()


def send(session: zenoh.Session, tid: str) -> zenoh.handlers.Handler[zenoh.Reply]:
    """A `check/home` get, not waited for."""
    body = msgpack.packb({"transaction_id": tid})
    return session.get(f"{BASE}/cmd/check/home", payload=body, timeout=5.0)


def reply_of(pending: zenoh.handlers.Handler[zenoh.Reply]) -> Reply:
    [r] = list(pending)
    sample = r.ok if r.ok is not None else r.err
    assert sample is not None
    return decode(Reply, sample.payload.to_bytes(), Format.MSGPACK)


def commanded(sink: ListEventSink, rig: Rig) -> list[str | None]:
    rig.loop.recorder.release()
    return [d.transaction_id for d, _, _ in sink.events if isinstance(d, CommandEvent)]


def until(condition: object, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.001)


def test_with_the_lock_free_a_command_runs_on_zenohs_thread_and_starts_no_other(
    session: zenoh.Session, machine: tuple[Rig, Commands, ListEventSink]
) -> None:
    rig, _, sink = machine
    threads: set[str] = set()
    run = rig.loop.execute

    def spy(*args: object, **kwargs: object) -> Reply:
        threads.add(threading.current_thread().name)
        return run(*args, **kwargs)  # type: ignore[arg-type]

    rig.loop.execute = spy  # type: ignore[method-assign]
    tids = [f"free-{next(_ids)}" for _ in range(5)]
    replies = [reply_of(send(session, tid)) for tid in tids]
    assert [r.transaction_id for r in replies] == tids and all(r.success for r in replies)
    assert commanded(sink, rig) == tids
    # Zenoh's own thread (here the asking one: a local query is delivered in place), neither a
    # callback thread of pyo3's nor the deferred one.
    assert threads and not any("pyo3" in n or n.startswith("cmd-") for n in threads), threads


def test_while_the_scan_holds_the_lock_commands_wait_in_order_and_a_later_one_queues_behind(
    session: zenoh.Session, machine: tuple[Rig, Commands, ListEventSink]
) -> None:
    rig, bus, sink = machine
    tids = [f"held-{next(_ids)}" for _ in range(4)]
    with rig.loop.lock:  # mid-cycle
        pending = [send(session, tid) for tid in tids[:3]]
        until(lambda: bus.deferred.pending == 3)
    # The lock is free now, but a later command must not overtake those still waiting.
    pending.append(send(session, tids[3]))
    replies = [reply_of(p) for p in pending]
    assert [r.transaction_id for r in replies] == tids and all(r.success for r in replies)
    assert commanded(sink, rig) == tids
    until(lambda: bus.deferred.pending == 0)


@pytest.mark.hazard("H47")
def test_a_stalled_loop_gets_busy_and_a_full_queue_is_refused(
    session: zenoh.Session,
    machine: tuple[Rig, Commands, ListEventSink],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rig, bus, sink = machine
    monkeypatch.setattr(commands, "LOCK_TIMEOUT_S", 0.2)
    bus.deferred.capacity = 2
    with rig.loop.lock:  # a scan stuck in a cycle
        waiting = [send(session, f"stuck-{i}") for i in range(2)]
        until(lambda: bus.deferred.pending == 2)
        refused = reply_of(send(session, "one-too-many"))
        first = reply_of(waiting[0])
    assert not refused.success and refused.error is not None
    assert refused.error.code is ErrorCode.BUSY and "queue full" in refused.error.message
    assert not first.success and first.error is not None
    assert first.error.code is ErrorCode.BUSY and "not responding" in first.error.message
    assert reply_of(waiting[1]).transaction_id == "stuck-1"
    assert "stuck-0" not in commanded(sink, rig)  # refused, not run later


def test_deferred_runs_in_order_on_one_thread_that_ends_when_idle() -> None:
    deferred = Deferred(capacity=8)
    ran: list[tuple[int, str]] = []
    gate = threading.Event()
    done = threading.Event()

    def job(i: int) -> None:
        gate.wait(5.0)
        ran.append((i, threading.current_thread().name))
        if i == 2:
            raise RuntimeError("a broken job")  # logged; the next one still runs
        if i == 4:
            done.set()

    for i in range(5):
        assert deferred.put(lambda i=i: job(i))
    assert deferred.pending == 5
    gate.set()
    assert done.wait(5.0)
    until(lambda: deferred.pending == 0)
    assert [i for i, _ in ran] == [0, 1, 2, 3, 4]
    assert len({name for _, name in ran}) == 1
    until(lambda: not any(t.name == "cmd-deferred" for t in threading.enumerate()))
    assert deferred.put(lambda: ran.append((5, threading.current_thread().name)))  # starts again
    until(lambda: len(ran) == 6)
