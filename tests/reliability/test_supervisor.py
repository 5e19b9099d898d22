"""`machine supervise`: a daemon that dies or freezes mid-ride leaves the outputs safe.

The supervisor runs the simulated world itself (behind a process-image file) and the daemon as
a child on the RevPi backend, so the world is the ground truth across the daemon's death: its
relays must be off by the time the supervisor announces FAULT_HW, and the restarted daemon comes
up not home, with its calibration.
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import pytest

from ride_machine.common.credentials import MACHINE, RIDER, env_name
from ride_machine.rider.client import CommandRefused, Rider
from ride_machine.schema.codec import Format, encode
from ride_machine.schema.commands import Reply, RotateStep, Session, TiltStep
from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import FAULT_STATES, FaultCode, MachineState, Status
from tests import freeze
from tests.integration.support import STEP_TIMEOUT_S, Preparation
from tests.procs import STOP_TIMEOUT_S, Daemon
from tests.reliability.support import (
    ACL_PROFILE,
    StatusFeed,
    make_identities,
    rider_as,
    start_machine,
    supervisor_child,
)

pytestmark = pytest.mark.integration

LONG_RIDE = Session(name="long", steps=[TiltStep(degrees=30.0), RotateStep(revolutions=40)])
"""Twenty seconds of rotation at the fast config: the daemon dies in the middle of it."""


@pytest.fixture
def supervised(tmp_path: Path) -> Iterator[Daemon]:
    daemon = start_machine(tmp_path, command="supervise")
    try:
        yield daemon
    finally:
        daemon.stop()


def ride_until_rotating(r: Rider, feed: StatusFeed, tries: int = 3) -> Reply:
    """Calibrate what is missing, home, start the long ride; return while the rotate relay is on.

    Rides again after a fault the loaded host caused (`Preparation`): the supervisor's world
    thread, late, left the tilt's sensor unchanged for a check window (`TILT_NOT_FOLLOWING`), or
    did so during the tilt's calibration stroke, whose gain then made the tilt too fast
    (`TILT_SPEED_IMPLAUSIBLE`); the world must have counted the late step. Any other fault
    fails the test."""
    reply, _ = Preparation(r).ride(
        lambda: r.start(LONG_RIDE),
        lambda reply: feed.until(partial(_rotating_or_faulted, since=reply.timecode)),
        tries=tries,
    )
    assert r.sim("world").relays["O_1"], "the rotate relay is on mid-ride"
    return reply


def _rotating_or_faulted(status: Status, since: float) -> bool:
    if status.time < since:
        return False
    session = status.session
    return (session is not None and session.revolutions_done >= 1) or (status.state in FAULT_STATES)


def daemon_died(status: Status) -> bool:
    return (
        status.state is MachineState.FAULT_HW
        and status.fault is not None
        and status.fault.code is FaultCode.DAEMON_DIED
    )


def image_relays(daemon: Daemon) -> dict[str, bool]:
    """The relay bits in the supervisor's process-image file, read without revpimodio2."""
    return freeze.image_relays(daemon.data_dir)


@pytest.mark.hazard("H03")
def test_sigkill_mid_ride_outputs_safe_then_restart_not_home_with_calibration(
    supervised: Daemon,
) -> None:
    with supervised.rider(timeout=3.0) as r:
        feed = StatusFeed(r)
        try:
            ride = ride_until_rotating(r, feed)
            ended: list[Completion] = []
            waiter = threading.Thread(target=lambda: ended.append(r.wait_done(ride, 30.0)))
            waiter.start()
            child = supervisor_child(supervised)
            t_kill = time.monotonic()
            os.kill(child, signal.SIGKILL)
            down = feed.until(daemon_died)
            t_down = time.monotonic()
            world = r.sim("world")
            assert not any(world.relays.values()), world.relays
            assert not any(image_relays(supervised).values())
            assert "SIGKILL" in down.fault.message if down.fault else False
            assert down.previous_state is MachineState.RUNNING
            # While the daemon is down the supervisor answers for the machine.
            assert r.status().state is MachineState.FAULT_HW
            with pytest.raises(CommandRefused) as refused:
                r.home()
            assert refused.value.error.code is ErrorCode.NOT_AVAILABLE
            # The ride ended with the daemon: its one notice comes from the supervisor.
            waiter.join(30.0)
            assert ended and ended[0].outcome is Outcome.FAULT_HW, ended
            assert ended[0].code == "DAEMON_DIED"
            assert ended[0].transaction_id == ride.transaction_id
            back = feed.until(lambda s: not daemon_died(s))
            t_back = time.monotonic()
        finally:
            feed.close()
        assert back.state is MachineState.WARNING_NOT_HOME, back
        assert back.calibrated.tilt and back.calibrated.rotate
        assert not back.homed.tilt and not back.homed.rotate
        assert not any(r.sim("world").relays.values())
    assert supervisor_child(supervised) != child
    print(  # the numbers for the report (pytest -s)
        f"\nSIGKILL → FAULT_HW seen {1e3 * (t_down - t_kill):.1f} ms;"
        f" → restarted daemon's status {t_back - t_kill:.2f} s"
    )


FROZEN = ("the daemon stopped answering", "the daemon's scan loop stopped cycling")
"""How the supervisor tells a frozen daemon: its token went, or its scan stopped for `--hang`.
Its link's lease is `--hang` (3 s here) too, so either can be first."""


@pytest.mark.hazard("H02")
def test_frozen_daemon_is_caught_and_replaced(supervised: Daemon) -> None:
    with supervised.rider(timeout=3.0) as r:
        feed = StatusFeed(r)
        try:
            ride_until_rotating(r, feed)
            child = supervisor_child(supervised)
            t_stop = time.monotonic()
            os.kill(child, signal.SIGSTOP)  # alive, holding its relays, answering nothing
            down = feed.until(daemon_died)
            t_down = time.monotonic()
            assert not any(r.sim("world").relays.values())
            assert down.fault is not None and down.fault.message.startswith(FROZEN), down
            back = feed.until(lambda s: not daemon_died(s))
        finally:
            feed.close()
        assert back.state is MachineState.WARNING_NOT_HOME, back
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)  # the frozen process was killed, not left behind
    # the log says where its threads were as it was killed: every one stopped, as the kernel says
    said = next(x for x in supervised.log().splitlines() if f"child_threads pid={child} " in x)
    states = set(re.findall(r"[^ ';]+:([A-Za-z])(?::\S+)? ran=", said.split(" since=")[0]))
    assert states == {"T"}, said
    print(f"\nSIGSTOP → FAULT_HW seen {t_down - t_stop:.2f} s (--hang and the lease: 3 s here)")


def test_a_daemon_frozen_for_less_than_the_hang_limit_wakes_up_and_stays(
    supervised: Daemon,
) -> None:
    """`--hang` is the limit (3 s here: three of the fast config's 1 s watchdog limits), not the
    profile's 1 s lease: a daemon SIGSTOPped for 1.5 s wakes up on the bus, the same process,
    and answers. Before, one end of its link dropped it at the lease and it was killed and
    replaced (run 14: a daemon a loaded host stopped whole for over a second)."""
    with supervised.rider(timeout=3.0) as r:
        before = r.status().state
        child = supervisor_child(supervised)
        os.kill(child, signal.SIGSTOP)
        time.sleep(1.5)  # the freeze: longer than the lease, shorter than --hang
        os.kill(child, signal.SIGCONT)
        resumed = supervised.has_logged(f"daemon_resumed pid={child}", STEP_TIMEOUT_S)
        assert resumed, supervised.log()[-2000:]
        assert r.status().state is before
    assert supervisor_child(supervised) == child
    log = supervised.log()
    assert "event=daemon_down" not in log and "event=child_threads" not in log, log[-2000:]


def test_sigterm_stops_the_child_cleanly_and_leaves_outputs_safe(supervised: Daemon) -> None:
    with supervised.rider(timeout=3.0) as r:
        feed = StatusFeed(r)
        try:
            ride_until_rotating(r, feed)
        finally:
            feed.close()
        # Still riding (this Rider is connected, so no rider-loss pause): relays on in the image.
        child = supervisor_child(supervised)
        assert any(image_relays(supervised).values())
        supervised.proc.send_signal(signal.SIGTERM)
        assert supervised.proc.wait(STOP_TIMEOUT_S) == 0
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)
    assert not any(image_relays(supervised).values())
    log = supervised.log()
    assert "event=stopped code=0" in log  # the daemon's own clean shutdown
    assert "event=daemon_down" not in log


@pytest.mark.hazard("H32")
def test_supervisor_router_enforces_the_acl_profile(tmp_path: Path) -> None:
    ids = make_identities(tmp_path / "users")
    rider_env = ids.env(RIDER, "rider")
    daemon = start_machine(
        tmp_path,
        command="supervise",
        profile=ACL_PROFILE,
        env={
            env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary),
            **ids.env(MACHINE, "machine"),
        },
        rider_env=rider_env,
    )
    try:
        with (
            rider_as(daemon, rider_env) as r,
            rider_as(daemon, ids.env(RIDER, "monitor"), timeout=1.5) as m,
        ):
            assert r.check_calibration().ok is False  # through the router to the child
            assert m.status().machine_id == "m1"  # the monitor reads
            denied = list(m.session.get(f"{m.base}/cmd/home", payload=b'{"transaction_id":"x"}'))
            assert denied == []
            # A monitor cannot speak for the machine: its fake status never reaches a Rider.
            feed = StatusFeed(r)
            try:
                fake = Status(machine_id="m1", state=MachineState.DONE, seq=0, cycle=0, time=0.0)
                m.session.put(f"{m.base}/status", encode(fake), encoding=Format.MSGPACK.value)
                sent = time.time()
                seen = [feed.next()]
                while seen[-1].time < sent:
                    seen.append(feed.next())
            finally:
                feed.close()
            assert all(s.time > 0 for s in seen)
    finally:
        daemon.stop()


def test_supervisor_refuses_an_acl_router_without_the_daemon_identity(tmp_path: Path) -> None:
    ids = make_identities(tmp_path / "users")
    daemon = start_machine(
        tmp_path,
        command="supervise",
        profile=ACL_PROFILE,
        env={env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary)},
        wait=False,
    )
    assert daemon.proc.wait(STOP_TIMEOUT_S) == 2
    assert "MACHINE_ZENOH_USER" in daemon.log()
