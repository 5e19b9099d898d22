"""The Rider client against real daemons over tcp/127.0.0.1: errors, discovery, asyncio."""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
from pathlib import Path

import pytest
import zenoh

from ride_machine.rider.client import (
    AmbiguousMachine,
    AsyncRider,
    BusError,
    CommandRefused,
    MachineTimeout,
    NoMachine,
    Rider,
    Throttle,
    Update,
)
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.codec import encode
from ride_machine.schema.commands import Command, CommandRequest, ReplyCode
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.io import IoValue
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import SETTLED, STEP_TIMEOUT_S, fast_daemon, module_machine
from tests.procs import Daemon, free_port, write_zenoh_config

pytestmark = pytest.mark.integration


machine = module_machine("client")


def nowhere(tmp_path: Path, machine_id: str | None = "m1") -> Rider:
    """A Rider pointed at a loopback port nobody listens on."""
    return Rider(
        machine_id,
        connect=[f"tcp/127.0.0.1:{free_port()}"],
        zenoh_config_path=write_zenoh_config(tmp_path),
        timeout=0.3,
    )


def test_no_machine_raises_machine_timeout(tmp_path: Path) -> None:
    with nowhere(tmp_path) as rider:
        with pytest.raises(MachineTimeout, match="machine/m1/status"):
            rider.status()
        with pytest.raises(MachineTimeout, match="machine/m1/cmd/home"):
            rider.home()
        with pytest.raises(MachineTimeout):
            rider.wait_for({MachineState.IDLE}, timeout=0.5)


def test_no_machine_alive_raises_no_machine_when_none_is_named(tmp_path: Path) -> None:
    with nowhere(tmp_path, None) as rider:
        assert rider.machines() == []
        with pytest.raises(NoMachine):
            rider.status()


def test_a_refusal_raises_command_refused_with_the_error_code(tmp_path: Path) -> None:
    # A daemon of its own: the module's daemon is calibrated by whichever test ran before, and
    # this one needs a never calibrated machine in any test order.
    with fast_daemon(tmp_path) as daemon, daemon.rider() as rider:
        assert not rider.status().calibrated.rotate
        with pytest.raises(CommandRefused) as refused:
            rider.start()
        assert refused.value.error.code is ErrorCode.NOT_CALIBRATED
        assert refused.value.reply.command == Command.START.value
        assert refused.value.reply.transaction_id is not None
        with pytest.raises(CommandRefused) as wrong:
            rider.pause()
        assert wrong.value.error.code is ErrorCode.WRONG_STATE
        assert "NOT_CALIBRATED" in str(refused.value)
        # check=False hands the refusal back as a value instead.
        reply = rider.command(Command.RESUME, check=False)
        assert not reply.success and reply.error is not None
        assert reply.error.code is ErrorCode.WRONG_STATE


def test_a_given_transaction_id_is_sent_as_is_and_replayed(machine: Daemon) -> None:
    with machine.rider() as rider:
        request = CommandRequest(transaction_id="client-fixed-1")
        first = rider.command(Command.CHECK_CALIBRATION, request)
        again = rider.command(Command.CHECK_CALIBRATION, request)
    assert first.transaction_id == "client-fixed-1"
    assert again == first


def test_watch_streams_status_io_and_axis_updates_during_motion(machine: Daemon) -> None:
    with machine.rider() as rider:
        reply = rider.calibrate_tilt()
        kinds: set[type] = set()
        for update in rider.watch(timeout=STEP_TIMEOUT_S):
            kinds.add(type(update))
            done = isinstance(update, Status) and update.time >= reply.timecode
            if done and update.state in SETTLED:
                break
        assert kinds == {Status, IoValue, AxisRecord}
        assert rider.status().calibrated.tilt


def test_diag_reset_replies_with_the_counters_before_it_and_restarts_them(
    machine: Daemon,
) -> None:
    with machine.rider() as rider:
        before = rider.diag()
        old = rider.diag(reset=True)
        after = rider.diag()
    assert old.since == before.since and old.cycles >= before.cycles  # not yet reset
    assert after.since >= old.time > before.since  # reset on the scan thread after the reply
    assert after.cycles >= old.cycles  # the cycle count is not one of the reset counters


def test_subscribe_delivers_decoded_updates_and_the_machines_presence(tmp_path: Path) -> None:
    updates: queue.Queue[Update] = queue.Queue()
    presence: queue.Queue[bool] = queue.Queue()
    with (
        fast_daemon(tmp_path) as daemon,
        daemon.rider() as rider,
        rider.subscribe(("status", "diag/cycle"), updates.put, presence.put),
    ):
        assert presence.get(timeout=STEP_TIMEOUT_S) is True  # the token's history
        kinds: set[type] = set()
        for _ in range(1000):  # a heartbeat every 0.2 s, diagnostics every 0.5 s
            kinds.add(type(updates.get(timeout=STEP_TIMEOUT_S)))
            if kinds == {Status, CycleDiag}:
                break
        assert kinds == {Status, CycleDiag}
        daemon.stop()
        assert presence.get(timeout=STEP_TIMEOUT_S) is False


def test_zenoh_errors_surface_as_bus_errors(machine: Daemon) -> None:
    with machine.rider() as rider:
        with pytest.raises(BusError, match="cannot subscribe under machine/m1: Invalid Key"):
            rider.subscribe(("status", "io//x"), lambda update: None)
        with pytest.raises(BusError, match="cannot query machine/m1/params/a//b") as got:
            rider.param("a//b")
        assert " at /" not in str(got.value)
        assert rider.status().machine_id == "m1"  # the session still works


def test_two_machines_alive_and_none_named_is_ambiguous(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    with fast_daemon(tmp_path / "a", "a") as a, fast_daemon(tmp_path / "b", "b") as b:
        both = [a.endpoint, b.endpoint]
        conf = write_zenoh_config(tmp_path)
        with Rider(None, connect=both, zenoh_config_path=conf) as rider:
            assert [m.id for m in rider.machines()] == ["a", "b"]
            with pytest.raises(AmbiguousMachine, match="a, b"):
                rider.status()
        with Rider("b", connect=both, zenoh_config_path=conf) as rider:
            assert rider.status().machine_id == "b"


def test_async_rider_commands_reads_and_watches(machine: Daemon) -> None:
    async def session() -> tuple[Status, list[Status]]:
        async with AsyncRider(
            "m1", connect=[machine.endpoint], zenoh_config_path=machine.zenoh_config
        ) as rider:
            status, diag, points = await asyncio.gather(rider.status(), rider.diag(), rider.io())
            assert status.machine_id == "m1" and diag.cycles > 0 and points
            with pytest.raises(CommandRefused) as refused:
                await rider.resume()
            assert refused.value.error.code is ErrorCode.WRONG_STATE
            reply = await rider.calibrate_rotate()
            assert reply.code is ReplyCode.RESP_CALIBRATION_ACCEPTED
            seen: list[Status] = []
            async for update in rider.watch(("status",), timeout=STEP_TIMEOUT_S):
                assert isinstance(update, Status)
                if update.time >= reply.timecode:
                    seen.append(update)
                    if update.state in SETTLED:
                        break
            return await rider.status(), seen

    final, seen = asyncio.run(asyncio.wait_for(session(), timeout=60))
    assert seen[0].state is MachineState.CALIBRATING
    assert final.calibrated.rotate


def test_async_watch_ends_cleanly_once_its_event_loop_is_gone(machine: Daemon) -> None:
    """The thread feeding an abandoned watch must not die on the closed loop."""

    async def first_update() -> Update:
        async with AsyncRider(
            "m1", connect=[machine.endpoint], zenoh_config_path=machine.zenoh_config
        ) as rider:
            async for update in rider.watch(("status",), timeout=1.0):
                return update
        raise AssertionError("no update")

    errors: list[BaseException | None] = []
    earlier = set(threading.enumerate())
    previous = threading.excepthook
    threading.excepthook = lambda args: errors.append(args.exc_value)
    try:
        assert isinstance(asyncio.run(asyncio.wait_for(first_update(), 30)), Status)
        for thread in set(threading.enumerate()) - earlier:
            if thread.name == "rider-watch":
                thread.join(STEP_TIMEOUT_S)  # its watch ends after 1 s without updates
                assert not thread.is_alive()
    finally:
        threading.excepthook = previous
    assert not errors, errors


@pytest.mark.hazard("H34", "H35", "H51")
def test_the_pinned_holder_and_its_supervisor_may_answer_and_no_one_else() -> None:
    from ride_machine.rider.client import Holders

    known = Holders()
    known.update("holder", "a", True)
    assert known.pinned == "a"
    known.update("supervisor", "s", True)
    assert known.allows("a") and known.allows("s") and not known.allows("rogue")
    known.update("holder", "b", True)  # a second daemon with the id: nobody is trusted
    assert known.pinned == "a" and not known.allows("a") and not known.allows("b")
    known.update("holder", "b", False)
    assert known.allows("a")
    known.update("holder", "a", False)  # the daemon restarts under a new session id
    known.update("holder", "a2", True)
    assert known.pinned == "a2" and not known.allows("a")


def test_the_machine_a_key_is_under_is_remembered_within_a_bound() -> None:
    from ride_machine.rider.client import KEY_CACHE

    rider = Rider("m1")  # not opened: the key arithmetic needs no session
    cases = {
        "machine/m1/cmd/home": "m1",
        "machine/other/status": "other",
        "machine/*/status": None,
        "machine/$*x/status": None,
        "site/m1/status": None,
        "machine": None,
    }
    for _ in range(2):  # computed, then remembered: the same answers
        assert {key: rider.transport.pins.machine_in(key) for key in cases} == cases
    for i in range(3 * KEY_CACHE):
        assert rider.transport.pins.machine_in(f"machine/m{i}/status") == f"m{i}"
        assert len(rider.transport.pins._machine_of) <= KEY_CACHE
    assert rider.transport.pins.machine_in("machine/*/status") is None


@pytest.mark.hazard("H34")
def test_subscribe_drops_samples_of_any_session_but_the_machine(
    machine: Daemon, caplog: pytest.LogCaptureFixture
) -> None:
    """A peer that publishes under the machine's keys (with no source, or naming itself) is
    not the machine: a pinned Rider drops its IO samples and still gets the machine's own,
    and says so once, not once per sample (a flood of them must not become a flood of lines).
    """
    caplog.set_level(logging.WARNING, logger="rider.client")
    updates: queue.Queue[Update] = queue.Queue()
    rogue_at = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config.from_file(str(machine.zenoh_config))
    conf.insert_json5("listen/endpoints", f'["{rogue_at}"]')
    conf.insert_json5("connect/endpoints", f'["{machine.endpoint}"]')
    with (
        zenoh.open(conf) as rogue,
        Rider(
            "m1", connect=[machine.endpoint, rogue_at], zenoh_config_path=machine.zenoh_config
        ) as rider,
    ):
        point = rider.io()[0]
        with rider.subscribe(("io/**", "diag/cycle"), updates.put):
            first = updates.get(timeout=STEP_TIMEOUT_S)  # the machine's own (diag or IO)
            assert rider.holders("m1").pinned is not None
            fake = encode(point.model_copy(update={"time": 12345.0}))
            key = f"machine/m1/io/{point.kind}/{point.name}"
            pub = rogue.declare_publisher(key)
            for _ in range(20):
                rogue.put(key, fake)  # no source at all
                pub.put(fake)  # its own session as the source
            seen: list[Update] = [first]
            while sum(isinstance(u, CycleDiag) for u in seen) < 2:  # diag every 0.5 s
                seen.append(updates.get(timeout=STEP_TIMEOUT_S))
            pub.undeclare()
    assert not [u for u in seen if isinstance(u, IoValue) and u.time == 12345.0]
    warned = [r.getMessage() for r in caplog.records if "event=foreign_sample" in r.getMessage()]
    assert len(warned) == 1, warned  # 40 dropped within a second: the first one is said
    assert f"key={key}" in warned[0] and "suppressed=0" in warned[0]


def test_a_repeated_line_is_said_first_then_at_most_once_per_period_with_its_count() -> None:
    now = [100.0]
    throttle = Throttle(10.0, clock=lambda: now[0])
    assert throttle.allow() == 0
    assert [throttle.allow() for _ in range(5)] == [None] * 5
    now[0] = 109.9
    assert throttle.allow() is None
    now[0] = 110.0
    assert throttle.allow() == 6  # the six held back since the first
    assert throttle.allow() is None
    now[0] = 500.0
    assert throttle.allow() == 1
