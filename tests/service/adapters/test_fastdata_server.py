"""The FastData UDP server, over real sockets on 127.0.0.1 (port 0, so tests never collide)."""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterator, Mapping

import pytest

from ride_machine.schema.axes import AxisRecord, PnStatus
from ride_machine.schema.commands import Command
from ride_machine.schema.fastdata import (
    MAX_REQUEST_BYTES,
    SERVERDATA_VERSION,
    USER_REGISTER_LENGTH,
    ServerData,
    decode,
)
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.fastdata import (
    DRV_STAT_FAULT,
    FastDataServer,
    RequestBudget,
    UserRegisters,
    build_reply,
    to_fast_axis,
)
from tests.rig import FakeClock, Rig

TIMEOUT = 2.0


def record(axis: str, number: int, **over: object) -> AxisRecord:
    values: dict[str, object] = {
        "axis": axis,
        "axis_number": number,
        "pn_status": int(PnStatus.SETTLED | PnStatus.DRIVE_ENABLED),
        "cycle": 100 + number,
        "position_cmd": 10.0 + number,
        "position_fb": 11.0 + number,
        "velocity_cmd": 12.0 + number,
        "velocity_fb": 13.0 + number,
        "time": 1.0e9,
    }
    values.update(over)
    return AxisRecord.model_validate(values)


AXES = {"rotate": record("rotate", 1), "tilt": record("tilt", 2)}


@pytest.fixture
def server() -> Iterator[FastDataServer]:
    srv = FastDataServer(lambda: AXES, host="127.0.0.1", port=0)
    srv.start()
    try:
        yield srv
    finally:
        srv.close()


@pytest.fixture
def client() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(TIMEOUT)
    try:
        yield sock
    finally:
        sock.close()


def ask(sock: socket.socket, server: FastDataServer, mask: bytes) -> ServerData:
    sock.sendto(mask, server.address)
    data, _ = sock.recvfrom(65535)
    return decode(data)


# ---------------------------------------------------------------------- record mapping
def test_every_axis_record_field_maps_to_its_fastdata_field() -> None:
    fast = to_fast_axis(
        record(
            "tilt", 2, pn_status=int(PnStatus.MOVING), cycle=77, drive_cmd=3000.0, drive_fb=2900.0
        )
    )
    assert fast.as_dict() == {
        "pnStatus": int(PnStatus.MOVING),
        "axisnumber": 2,
        "drvStat": 0,
        "bus_cycle_num": 77,
        "pCmd": 12.0,
        "pFb": 13.0,
        "pExt": 0.0,
        "cCmd": 3000.0,  # position command in drive units (tilt: raw counts), not a current
        "cFb": 2900.0,
        "vCmd": 14.0,
        "vFb": 15.0,
        "aCmd": 0.0,
        "tAddCmd": 0.0,
        "tFb": 0.0,
    }


def test_drive_fault_bit_sets_drvstat() -> None:
    bits = int(PnStatus.DRIVE_FAULT | PnStatus.SETTLED)
    fast = to_fast_axis(record("rotate", 1, pn_status=bits))
    assert fast.drvStat == DRV_STAT_FAULT != 0
    assert fast.pnStatus == bits


def test_loop_cycle_overrides_record_cycle_and_wraps_at_32_bits() -> None:
    assert to_fast_axis(record("rotate", 1, cycle=5), cycle=9).bus_cycle_num == 9
    assert to_fast_axis(record("rotate", 1), cycle=2**32 + 3).bus_cycle_num == 3


def test_reply_carries_the_version_and_user_registers_of_full_length() -> None:
    reply = decode(build_reply(b"\x01\x01", AXES))
    assert reply.version == SERVERDATA_VERSION
    assert reply.ints == (0,) * USER_REGISTER_LENGTH
    assert reply.doubles == (0.0,) * USER_REGISTER_LENGTH
    regs = UserRegisters.of([7, -(2**31)], [1.5])
    reply = decode(build_reply(b"\x01", AXES, registers=regs))
    assert reply.ints == (7, -(2**31)) + (0,) * (USER_REGISTER_LENGTH - 2)
    assert reply.doubles == (1.5,) + (0.0,) * (USER_REGISTER_LENGTH - 1)
    assert [a.axisnumber for a in reply.axes] == [1]


def test_axes_outside_the_mask_range_are_never_sent() -> None:
    odd = {"a": record("a", -1), "b": record("b", 300), "c": record("c", 2, pn_status=2**40)}
    reply = decode(build_reply(b"\x01" * MAX_REQUEST_BYTES, odd))
    assert [(a.axisnumber, a.pnStatus) for a in reply.axes] == [(2, 2**40 & 0xFFFFFFFF)]


# ---------------------------------------------------------------------------- over UDP
@pytest.mark.parametrize(
    ("mask", "numbers"),
    [
        (b"\x01", [1]),  # seed 002: cell i asks for axis number i + 1
        (b"\x00\x01", [2]),
        (b"\x00\xff", [2]),
        (b"\x01\x01", [1, 2]),
        (b"\x07\x00\x00", [1]),
        (b"\x00\x00\x00\x01", []),
        (b"\x00" * MAX_REQUEST_BYTES, []),
        (b"\x01" * MAX_REQUEST_BYTES, [1, 2]),
    ],
)
def test_axis_mask_selects_axes(
    server: FastDataServer, client: socket.socket, mask: bytes, numbers: list[int]
) -> None:
    reply = ask(client, server, mask)
    assert [a.axisnumber for a in reply.axes] == numbers


def test_one_axis_reply_holds_that_axis_values(
    server: FastDataServer, client: socket.socket
) -> None:
    (tilt,) = ask(client, server, b"\x00\x01").axes
    assert tilt == to_fast_axis(AXES["tilt"])
    assert (tilt.pFb, tilt.vFb, tilt.bus_cycle_num) == (13.0, 15.0, 102)


@pytest.mark.hazard("H30")
@pytest.mark.parametrize(
    "bad",
    [b"", b"\x01" * (MAX_REQUEST_BYTES + 1), b"\x01" * 4096, b"\xff" * 60000],
    ids=["empty", "one-too-many", "4k", "60k"],
)
def test_malformed_requests_are_ignored_and_server_keeps_answering(
    server: FastDataServer, client: socket.socket, bad: bytes
) -> None:
    client.sendto(bad, server.address)
    # Loopback keeps order and the server answers in order: had the bad request been answered,
    # that reply would be read here instead of the good one's.
    reply = ask(client, server, b"\x01\x01")
    assert [a.axisnumber for a in reply.axes] == [1, 2]
    server.close()  # joins the server thread: its counters are final
    assert server.stats.ignored == 1
    assert server.stats.replies == 1
    assert server.stats.requests == 2


def test_many_peers_and_a_burst_of_junk(server: FastDataServer) -> None:
    peers = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(4)]
    try:
        for i, p in enumerate(peers):
            p.settimeout(TIMEOUT)
            for n in range(50):
                p.sendto(b"" if n % 2 else b"\x01" * (MAX_REQUEST_BYTES + 1 + i), server.address)
        for i, p in enumerate(peers):
            assert [a.axisnumber for a in ask(p, server, bytes([0] * i + [1])).axes] == (
                [i + 1] if i < 2 else []
            )
    finally:
        for p in peers:
            p.close()
    server.close()  # joins the server thread: its counters are final
    assert server.stats.ignored == 200
    assert server.stats.replies == 4


def test_failing_snapshot_does_not_kill_the_server(client: socket.socket) -> None:
    calls = {"n": 0}

    def flaky() -> Mapping[str, AxisRecord]:
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("snapshot broke")
        return AXES

    with FastDataServer(flaky, port=0) as srv:
        client.sendto(b"\x01", srv.address)
        reply = ask(client, srv, b"\x01")
        assert [a.axisnumber for a in reply.axes] == [1]
        assert srv.stats.errors == 1


def test_port_zero_binds_an_ephemeral_port_and_close_releases_it() -> None:
    srv = FastDataServer(lambda: AXES, port=0)
    srv.start()
    port = srv.port
    assert port != 0
    srv.close()
    assert srv._thread is not None and not srv._thread.is_alive()
    srv.close()  # twice is harmless
    again = FastDataServer(lambda: AXES, port=port)
    again.start()  # the port is free again
    again.close()


def test_close_without_start_is_harmless() -> None:
    FastDataServer(lambda: AXES, port=0).close()


def test_busy_port_fails_at_start_with_oserror() -> None:
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("127.0.0.1", 0))
    try:
        srv = FastDataServer(lambda: AXES, port=taken.getsockname()[1])
        with pytest.raises(OSError):
            srv.start()
        srv.close()
    finally:
        taken.close()


def test_start_twice_is_refused(server: FastDataServer) -> None:
    with pytest.raises(RuntimeError, match="already started"):
        server.start()


def test_budget_allows_a_burst_then_the_rate() -> None:
    clock = FakeClock(0.0)
    budget = RequestBudget(rate=100.0, burst=3, clock=clock)
    assert [budget.take() for _ in range(3)] == [0.0, 0.0, 0.0]
    assert budget.take() == pytest.approx(0.01)
    clock.advance(0.005)
    assert budget.take() == pytest.approx(0.005)
    clock.advance(0.005)
    assert budget.take() == 0.0
    clock.advance(100.0)  # a long quiet spell refills only up to the burst
    assert [budget.take() for _ in range(4)][-1] > 0.0


def test_budget_refuses_nonsense_settings() -> None:
    with pytest.raises(ValueError, match="rate > 0"):
        RequestBudget(rate=0.0, burst=1, clock=FakeClock())
    with pytest.raises(ValueError, match="burst >= 1"):
        RequestBudget(rate=10.0, burst=0.5, clock=FakeClock())


def test_requests_beyond_the_rate_are_delayed_not_lost(client: socket.socket) -> None:
    with FastDataServer(lambda: AXES, port=0, max_rate=200.0) as srv:
        for i in range(30):
            client.sendto(bytes([0] * (i % 2) + [1]), srv.address)
        got = [decode(client.recvfrom(65535)[0]) for _ in range(30)]
    assert [r.axes[0].axisnumber for r in got] == [i % 2 + 1 for i in range(30)]


# ------------------------------------------------------------------- beside the scan loop
def _storm(server: FastDataServer, peers: int, per_peer: int) -> list[ServerData]:
    """Several clients firing requests at once; returns every reply they got."""
    replies: list[ServerData] = []
    failures: list[BaseException] = []
    lock = threading.Lock()

    def fire() -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.settimeout(TIMEOUT)
            try:
                for _ in range(per_peer):
                    got = ask(s, server, b"\x01\x01")
                    with lock:
                        replies.append(got)
            except OSError as exc:
                failures.append(exc)

    threads = [threading.Thread(target=fire) for _ in range(peers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not any(t.is_alive() for t in threads)
    assert failures == []
    return replies


@pytest.mark.hazard("H30")
def test_storm_never_touches_the_loop() -> None:
    """The server only reads the published dict: no inbox task, no step, no loop lock."""
    rig = Rig().ready()
    loop = rig.loop
    threads: set[str] = set()

    def snapshot() -> Mapping[str, AxisRecord]:
        threads.add(threading.current_thread().name)
        return loop.published.axes

    cycle_before, handled_before = loop.cycle, loop.commands_handled
    # Hold the loop's only lock for the whole storm: a server that needed it would hang.
    with FastDataServer(snapshot, port=0, cycle=lambda: loop.cycle) as srv, loop.inbox._lock:
        replies = _storm(srv, peers=4, per_peer=250)
    assert len(replies) == 1000
    assert threads == {"fastdata"}
    assert (loop.cycle, loop.commands_handled, len(loop.inbox)) == (
        cycle_before,
        handled_before,
        0,
    )
    assert all(r.axes[0].bus_cycle_num == cycle_before for r in replies)


def test_loop_keeps_cycling_while_stormed_and_replies_follow_it() -> None:
    rig = Rig().ready()
    loop = rig.loop
    assert rig.send(Command.START).success
    rig.run_until(lambda: rig.state is MachineState.RUNNING)
    stormed: list[list[ServerData]] = []
    with FastDataServer(lambda: loop.published.axes, port=0, cycle=lambda: loop.cycle) as srv:
        t = threading.Thread(target=lambda: stormed.append(_storm(srv, peers=2, per_peer=300)))
        t.start()
        steps = 0
        while t.is_alive() and steps < 100_000:  # the loop runs on, never waiting for the server
            rig.step()
            steps += 1
        t.join(30)
        final = ask_once(srv, b"\x01\x01")
    replies = stormed[0]
    assert len(replies) == 600
    assert steps > 0
    cycles = [r.axes[0].bus_cycle_num for r in replies]
    assert min(cycles) >= 1 and max(cycles) <= loop.cycle
    rotate = loop.published.axes["rotate"]
    assert final.axes[0] == to_fast_axis(rotate, loop.cycle)


def ask_once(server: FastDataServer, mask: bytes) -> ServerData:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(TIMEOUT)
        return ask(s, server, mask)


def test_records_follow_the_live_loop() -> None:
    rig = Rig().ready()
    loop = rig.loop
    snapshot: Callable[[], Mapping[str, AxisRecord]] = lambda: loop.published.axes  # noqa: E731
    with FastDataServer(snapshot, port=0, cycle=lambda: loop.cycle) as srv:
        assert rig.send(Command.START).success
        rig.run_until(lambda: bool(loop.published.axes["tilt"].pn_status & PnStatus.MOVING))
        moving = ask_once(srv, b"\x00\x01").axes[0]
        assert moving.pnStatus & PnStatus.MOVING
        assert moving.pFb == loop.published.axes["tilt"].position_fb
        assert moving.bus_cycle_num == loop.cycle
        rig.step(20)
        later = ask_once(srv, b"\x00\x01").axes[0]
        assert later.bus_cycle_num == moving.bus_cycle_num + 20
        assert later.pFb != moving.pFb
