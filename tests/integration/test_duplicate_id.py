"""One machine per id (issue 15, reproduction 1): two daemons with one id are never both in
charge. A second daemon refuses to start; two that meet at runtime (two network segments
joined by a router) both stop with DUPLICATE_ID; a Rider that hears both raises
`DuplicateMachine` (CLI exit 5) instead of printing one of the answers.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import pytest
from pydantic import BaseModel

from ride_machine.rider.cli import EXIT_DUPLICATE
from ride_machine.rider.client import DuplicateMachine, Rider
from ride_machine.schema.codec import Format, decode, encode
from ride_machine.schema.commands import CommandRequest, Reply
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import FaultCode, MachineState, Status
from tests.integration import rider_proc
from tests.integration.support import STEP_TIMEOUT_S, fast_args
from tests.procs import REPO, Daemon, run_rider, start_daemon
from tests.site.stand import Router

pytestmark = pytest.mark.integration

M = TypeVar("M", bound=BaseModel)
DUPLICATE = FaultCode.DUPLICATE_ID

ROUTER_CONFIG = """{
  mode: "router",
  scouting: { multicast: { enabled: false }, gossip: { enabled: true } },
  transport: { link: { tx: { lease: 1000, keep_alive: 4 } } },
}
"""
GOSSIP_CONFIG = """{
  mode: "peer",
  scouting: { multicast: { enabled: false }, gossip: { enabled: true } },
  transport: { link: { tx: { lease: 1000, keep_alive: 4 } } },
}
"""
"""Zenoh's default gossip (off in the other tests' config): a router that joins two segments
tells each daemon where the other is, and they link up directly."""


LONG = ("--revolutions", "40", "prepare", "start", "running", "hold")
"""20 s of motion at the fast config: still running when the segments are joined."""


def zid_of(daemon: Daemon) -> str:
    with daemon.rider(supervise=False) as r:
        r.status()
        pinned = r.holders(daemon.machine_id).pinned
    assert pinned is not None
    zid_of_endpoint[daemon.endpoint] = pinned
    return pinned


@contextlib.contextmanager
def daemon_in(tmp: Path, name: str, *extra: str) -> Iterator[Daemon]:
    directory = tmp / name
    directory.mkdir()
    gossip = directory / "gossip.json5"
    gossip.write_text(GOSSIP_CONFIG)
    extra = (*fast_args(directory), "--zenoh-config", str(gossip), *extra)
    daemon = start_daemon(directory, "m1", extra=list(extra))
    try:
        yield daemon
    finally:
        daemon.stop()


@contextlib.contextmanager
def router_between(tmp: Path, *daemons: Daemon) -> Iterator[str]:
    """A Zenoh router that connects to each daemon: the segments joined. Yields its endpoint."""
    config = tmp / "bridge.json5"
    config.write_text(ROUTER_CONFIG)
    router = Router(config, tmp, connect=[d.endpoint for d in daemons])
    router.start()
    try:
        yield router.endpoint
    finally:
        router.kill(signal.SIGTERM)


def own(daemon: Daemon, key: str, model: type[M], payload: bytes | None = None) -> M:
    """`key` answered by this daemon alone: a plain Zenoh query on a session linked to it only
    (a `Rider` would rightly refuse to talk to a machine id that two sessions hold)."""
    with daemon.rider(supervise=False) as r:
        kwargs = {} if payload is None else {"payload": payload}
        replies = list(r.session.get(f"machine/m1/{key}", timeout=5.0, **kwargs))
    assert len(replies) == 1 and replies[0].ok is not None, replies
    assert str(replies[0].replier_id.zid) == zid_of_endpoint[daemon.endpoint]
    return decode(model, replies[0].ok.payload.to_bytes(), Format.MSGPACK)


zid_of_endpoint: dict[str, str] = {}


def own_status_until(daemon: Daemon, done: Callable[[Status], bool]) -> Status:
    deadline = time.monotonic() + STEP_TIMEOUT_S
    while time.monotonic() < deadline:
        status = own(daemon, "status", Status)
        if done(status):
            return status
        time.sleep(0.1)
    raise AssertionError(f"{daemon.endpoint}: {status}\n{daemon.log()}")


def relays_off_at(daemon: Daemon) -> bool:
    return not any(own(daemon, "sim/world", SimWorldState).relays.values())


@pytest.mark.hazard("H35")
def test_a_second_daemon_with_a_live_id_refuses_to_start(tmp_path: Path) -> None:
    with daemon_in(tmp_path, "a") as first:
        first_zid = zid_of(first)
        second_dir = tmp_path / "b"
        second_dir.mkdir()
        second = start_daemon(
            second_dir,
            "m1",
            extra=[*fast_args(second_dir), "--connect", first.endpoint],
            wait=False,
        )
        try:
            assert second.proc.wait(STEP_TIMEOUT_S) == 1
        finally:
            second.stop()
        refusals = [line for line in second.log().splitlines() if "event=duplicate_id" in line]
        assert len(refusals) == 1, second.log()
        assert first_zid in refusals[0] and "action=refuse_start" in refusals[0]
        assert "event=started" not in second.log()
        # The first one never noticed anything: it holds its id alone and still takes commands.
        with first.rider(supervise=False) as r:
            assert r.status().fault is None
            assert r.check_home().ok is False


def riding(*daemons: Daemon) -> list[subprocess.Popen[str]]:
    """One Rider process per daemon, each riding the long session (`LONG`) on its segment."""
    return [
        subprocess.Popen(
            [*rider_proc.command(d.endpoint, d.zenoh_config, "m1", *LONG)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        for d in daemons
    ]


def rider_hearing(a: Daemon, b: Daemon, *args: str) -> subprocess.CompletedProcess[str]:
    """`rider ARGS` linked to both daemons, as a Rider on the joined network is."""
    linked = ("--connect", a.endpoint, "--connect", b.endpoint)
    return run_rider(*linked, "--zenoh-config", str(a.zenoh_config), *args)


@pytest.mark.hazard("H35")
def test_two_segments_joined_at_runtime_both_stop_with_duplicate_id(tmp_path: Path) -> None:
    with daemon_in(tmp_path, "a") as a, daemon_in(tmp_path, "b") as b:
        zids = sorted([zid_of(a), zid_of(b)])
        # Each segment alone: each machine rides a long session for its own Rider.
        riders = riding(a, b)
        try:
            for child in riders:
                rider_proc.read_step(child, "hold")
            with router_between(tmp_path, a, b):
                for daemon in (a, b):
                    status = own_status_until(
                        daemon, lambda s: s.fault is not None and s.fault.code is DUPLICATE
                    )
                    assert status.state is MachineState.FAULT_HW
                    assert status.fault is not None
                    assert all(z in status.fault.message for z in zids), status.fault
                    assert relays_off_at(daemon)
                    refused = own(
                        daemon, "cmd/home", Reply, encode(CommandRequest(transaction_id="h1"))
                    )
                    assert refused.error is not None
                    assert refused.error.code is ErrorCode.DUPLICATE_ID
            # A Rider that hears both never reports one of them as "the" machine.
            both = [a.endpoint, b.endpoint]
            with Rider("m1", connect=both, zenoh_config_path=a.zenoh_config) as r:
                with pytest.raises(DuplicateMachine) as caught:
                    r.status()
                assert sorted(caught.value.sessions) == zids
            done = rider_hearing(a, b, "--machine", "m1", "start")
            assert done.returncode == EXIT_DUPLICATE, done.stderr
            assert all(z in done.stderr for z in zids), done.stderr
            listed = rider_hearing(a, b, "machines")
            assert listed.returncode == EXIT_DUPLICATE, listed
            assert "CONFLICT" in listed.stdout and all(z in listed.stdout for z in zids)
            # One of them goes: the other is alone, takes commands again, and moved nothing.
            b.stop()
            status = own_status_until(
                a, lambda s: s.fault is not None and "alone" in s.fault.message
            )
            assert status.state is MachineState.FAULT_HW
            assert relays_off_at(a)
            home = own(a, "cmd/home", Reply, encode(CommandRequest(transaction_id="h2")))
            assert home.success, home
        finally:
            for child in riders:
                child.kill()
                child.wait(STEP_TIMEOUT_S)
