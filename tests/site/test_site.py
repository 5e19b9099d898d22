"""Three machines (a, b, c) and Riders meet through one router; every part is its own process.

a and c are clients of the router, b is a peer that also listens on its own loopback port; the
Riders connect only to the router. Sessions on a and b run at once while c must stay idle,
wildcard command keys are refused by every machine they reach, and a machine that dies leaves
the Riders' lists within about a second.
"""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
import zenoh

from ride_machine.rider.client import CommandRefused, Rider
from ride_machine.schema.codec import Format, decode, encode, pack
from ride_machine.schema.commands import CommandRequest, Reply, ReplyCode
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.io import IoValue
from ride_machine.schema.params import ParamSet
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import STEP_TIMEOUT_S, relays_off, settle, wait_cycles
from tests.procs import REPO, START_TIMEOUT_S
from tests.site.stand import Lines, Mode, Site, run_cli, wait_tokens

pytestmark = pytest.mark.integration

REVOLUTION_SLACK = 0.1
"""The rotate axis stops on the home switch: a session of 3 travels 3 revolutions ± a bit."""

GONE_BOUND_S = 5.0
"""Generous bound for a dead machine to leave the lists (lease 1 s; measured, see report)."""

QUIET_CYCLES = 30
"""Scan cycles a refused command is given to (wrongly) take effect before we look again."""


def machine_rider(abc: Site, machine_id: str) -> Rider:
    return abc.rider(machine_id, timeout=5.0)


@pytest.mark.parametrize("mode", ["client", "peer"])
def test_a_rider_on_the_router_lists_every_machine_with_state(abc: Site, mode: Mode) -> None:
    with abc.rider(None, mode, timeout=5.0) as r:
        if mode == "peer":
            # A peer Rider finds peer machines by gossip after it opens: wait for their tokens.
            wait_tokens(r.follow_machines(0.2), dict.fromkeys("abc", True), START_TIMEOUT_S)
        found = r.machines()
        assert [m.id for m in found] == ["a", "b", "c"]
        for m in found:
            assert m.state is not None, m
            assert m.uptime_s is not None and m.uptime_s > 0, m
    for mid in ("a", "b", "c"):
        with abc.rider(mid, mode, timeout=5.0) as one:
            if mode == "peer":
                wait_tokens(one.follow_machines(0.2), {mid: True}, START_TIMEOUT_S)
            assert one.status().machine_id == mid


def test_cli_lists_machines_and_wants_one_named_when_several_are_alive(abc: Site) -> None:
    listed = run_cli(abc.rider_cmd("--json", "machines"))
    assert listed.returncode == 0, listed.stderr
    rows = json.loads(listed.stdout)
    assert [row["id"] for row in rows] == ["a", "b", "c"]
    assert all(row["state"] in MachineState.__members__ for row in rows), rows
    assert all(row["uptime_s"] > 0 for row in rows), rows

    table = run_cli(abc.rider_cmd("machines"))
    assert table.returncode == 0, table.stderr
    assert [line.split()[0] for line in table.stdout.splitlines()] == ["a", "b", "c"]

    ambiguous = run_cli(abc.rider_cmd("status"))
    assert ambiguous.returncode == 4, (ambiguous.stdout, ambiguous.stderr)
    assert "several machines are alive (a, b, c)" in ambiguous.stderr
    assert "--machine" in ambiguous.stderr

    named = run_cli(abc.rider_cmd("--machine", "b", "--json", "status"))
    assert named.returncode == 0, named.stderr
    assert json.loads(named.stdout)["machine_id"] == "b"

    missing = run_cli(abc.rider_cmd("-m", "nobody", "status"))
    assert missing.returncode == 3, (missing.stdout, missing.stderr)
    assert "machine/nobody/status" in missing.stderr


def full_session(abc: Site, machine_id: str) -> dict[str, Any]:
    """Calibrate tilt, calibrate rotate, home, start, wait for DONE; what happened, in order."""
    with machine_rider(abc, machine_id) as r:
        began = time.monotonic()
        for command in (r.calibrate_tilt, r.calibrate_rotate):
            settled = settle(r, command())
            assert settled.state not in (MachineState.FAULT_HW, MachineState.FAULT_ESTOP), settled
        homed = settle(r, r.home())
        assert homed.state is MachineState.IDLE, homed
        before = r.sim("world")
        started = r.start()
        assert started.code is ReplyCode.RESP_START_ACCEPTED
        done = r.wait_for({MachineState.DONE}, STEP_TIMEOUT_S, after=started.timecode)
        return {
            "began": began,
            "ended": time.monotonic(),
            "done": done,
            "travelled": r.sim("world").revolutions - before.revolutions,
            "relays_off": relays_off(r),
        }


def watch_idle(abc: Site, machine_id: str, stop: threading.Event) -> list[Status | IoValue]:
    """Every status and relay update of one machine until `stop` (heartbeats keep it awake)."""
    seen: list[Status | IoValue] = []
    with machine_rider(abc, machine_id) as r:
        for update in r.watch(("status", "io/ro/**"), timeout=5.0):
            assert isinstance(update, Status | IoValue)
            seen.append(update)
            if stop.is_set():
                break
    return seen


def test_sessions_on_a_and_b_at_once_leave_c_idle(abc: Site) -> None:
    with machine_rider(abc, "c") as rc:
        c_before, c_world = rc.status(), rc.sim("world")
    stop = threading.Event()
    with ThreadPoolExecutor(3) as pool:
        watcher = pool.submit(watch_idle, abc, "c", stop)
        runs = [pool.submit(full_session, abc, mid) for mid in ("a", "b")]
        try:
            results = [run.result(timeout=4 * STEP_TIMEOUT_S) for run in runs]
        finally:
            stop.set()
        c_seen = watcher.result(timeout=STEP_TIMEOUT_S)

    for result in results:
        done: Status = result["done"]
        assert done.session is not None
        assert (done.session.revolutions_done, done.session.revolutions_total) == (3, 3)
        assert result["travelled"] == pytest.approx(3.0, abs=REVOLUTION_SLACK)
        assert result["relays_off"]
    a, b = results
    assert max(a["began"], b["began"]) < min(a["ended"], b["ended"]), "the runs did not overlap"

    states = {u.state for u in c_seen if isinstance(u, Status)}
    assert states == {c_before.state}, states
    assert not [u for u in c_seen if isinstance(u, IoValue) and u.value is True]
    with machine_rider(abc, "c") as rc:
        c_after, c_world_after = rc.status(), rc.sim("world")
        assert relays_off(rc)
    assert c_after.state is c_before.state
    assert c_after.calibrated == c_before.calibrated
    assert c_after.session is None
    assert (c_world_after.revolutions, c_world_after.tilt_deg) == (
        c_world.revolutions,
        c_world.tilt_deg,
    )
    assert not any(c_world_after.relays.values())


WILDCARD_COMMANDS = {
    "machine/*/cmd/home": ["a", "b", "c"],
    "machine/a/cmd/*": ["a"],
    "machine/a/cmd/**": ["a"],
    "machine/**/cmd/start": ["a", "b", "c"],
    "machine/b/cmd/ho$*": ["b"],
    "**/calibrate/tilt": ["a", "b", "c"],
}


def snapshot(abc: Site) -> dict[str, tuple[MachineState, SimWorldState]]:
    out = {}
    for mid in ("a", "b", "c"):
        with machine_rider(abc, mid) as r:
            out[mid] = (r.status().state, r.sim("world"))
    return out


def ask(abc: Site, key: str, payload: bytes) -> tuple[list[Reply], list[Reply]]:
    """One raw query through the router: its (error replies, ok replies), read as `Reply`."""
    with abc.rider(None, timeout=5.0) as r:
        # Every machine refuses on the same (wildcard) key: keep them all, no consolidation.
        replies = list(
            r.session.get(
                key,
                payload=payload,
                encoding=Format.MSGPACK.value,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=5.0,
            )
        )
    errs = [decode(Reply, x.err.payload.to_bytes(), Format.MSGPACK) for x in replies if x.err]
    oks = [decode(Reply, x.ok.payload.to_bytes(), Format.MSGPACK) for x in replies if x.ok]
    return errs, oks


def assert_bad_key(refusals: list[Reply], key: str) -> None:
    for refused in refusals:
        assert not refused.success
        assert refused.error is not None and refused.error.code is ErrorCode.BAD_KEY, refused
        assert "wildcards are not allowed in" in refused.error.message
        assert repr(key) in refused.error.message


def assert_nothing_moved(abc: Site, before: dict[str, tuple[MachineState, SimWorldState]]) -> None:
    """Give a wrongly accepted command some cycles to act, then compare every machine."""
    for mid in before:
        with machine_rider(abc, mid) as r:
            wait_cycles(r, QUIET_CYCLES)
    after = snapshot(abc)
    for mid, (state, world) in before.items():
        state_after, world_after = after[mid]
        assert state_after is state, (mid, state, state_after)
        moved = (world_after.revolutions, world_after.tilt_deg, world_after.estop_pressed)
        assert moved == (world.revolutions, world.tilt_deg, world.estop_pressed), mid
        assert not any(world_after.relays.values()), (mid, world_after.relays)


@pytest.mark.hazard("H31", "H51")
@pytest.mark.parametrize("key", list(WILDCARD_COMMANDS))
def test_a_wildcard_command_key_is_refused_by_every_machine_it_reaches(abc: Site, key: str) -> None:
    before = snapshot(abc)
    number = list(WILDCARD_COMMANDS).index(key)
    request = CommandRequest(transaction_id=f"wild-{number}", timecode=time.time())
    errors, others = ask(abc, key, encode(request))
    assert len(errors) == len(WILDCARD_COMMANDS[key]), errors
    assert_bad_key(errors, key)
    assert "command key" in errors[0].error.message  # type: ignore[union-attr]
    # A key like `machine/**/cmd/start` also matches `machine/<id>/sim/**`: refused there too.
    assert_bad_key(others, key)
    assert_nothing_moved(abc, before)


@pytest.mark.hazard("H31")
def test_wildcard_parameter_writes_and_fault_injections_are_refused(abc: Site) -> None:
    before = snapshot(abc)
    policy = "machine/*/params/rider_loss.policy"
    write = ParamSet(transaction_id="wild-param-1", value="ignore")
    errors, refusals = ask(abc, policy, encode(write))
    assert errors == [] and len(refusals) == 3, (errors, refusals)
    assert_bad_key(refusals, policy)
    assert refusals[0].transaction_id == "wild-param-1"

    estop = "machine/*/sim/estop"
    errors, refusals = ask(abc, estop, pack({"pressed": True}))
    assert errors == [] and len(refusals) == 3, (errors, refusals)
    assert_bad_key(refusals, estop)

    assert_nothing_moved(abc, before)
    for mid in ("a", "b", "c"):
        with machine_rider(abc, mid) as r:
            assert r.param("rider_loss.policy").value == "pause"
            assert not r.status().estop.active


@pytest.mark.hazard("H31")
def test_a_wildcard_machine_id_is_a_clear_error_in_the_client_and_the_cli(abc: Site) -> None:
    with abc.rider("*", timeout=5.0) as r, pytest.raises(CommandRefused) as refused:
        r.home()
    assert refused.value.error.code is ErrorCode.BAD_KEY
    cli = run_cli(abc.rider_cmd("-m", "*", "home"))
    assert cli.returncode == 1, (cli.stdout, cli.stderr)
    assert "BAD_KEY" in cli.stderr
    assert "wildcards are not allowed in a command key: 'machine/*/cmd/home'" in cli.stderr


@pytest.mark.hazard("H37", "H51")
def test_a_command_for_one_machine_is_answered_by_that_machine_only(abc: Site) -> None:
    request = CommandRequest(transaction_id="only-b-1", timecode=time.time())
    with abc.rider(None, timeout=5.0) as r:
        replies = list(
            r.session.get(
                "machine/b/cmd/check/calibration",
                payload=encode(request),
                encoding=Format.MSGPACK.value,
                timeout=5.0,
            )
        )
    assert len(replies) == 1
    sample = replies[0].ok
    assert sample is not None
    assert str(sample.key_expr) == "machine/b/cmd/check/calibration"
    reply = decode(Reply, sample.payload.to_bytes(), Format.MSGPACK)
    assert reply.success and reply.transaction_id == "only-b-1"


def _ctrl_c_as_in_a_terminal() -> None:
    """SIGINT's default action in the child, as a terminal's foreground job has it: a suite
    started in the background (`make test &` from a script) ignores SIGINT, and a child
    inherits an ignored signal across exec, so Ctrl-C would not reach the watch."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def watch_cli(abc: Site, seconds: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        abc.rider_cmd("--json", "machines", "--watch", "--for", str(seconds)),
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
        preexec_fn=_ctrl_c_as_in_a_terminal,  # noqa: PLW1509 - one signal reset before exec
    )


@pytest.fixture
def doomed(abc: Site, request: pytest.FixtureRequest) -> Iterator[str]:
    """A fourth machine for one test to kill or freeze; always gone at the end."""
    mid = f"doomed-{request.node.callspec.id.lower()}"
    abc.add_daemon(mid, "client")
    try:
        abc.wait_alive([mid])
        yield mid
    finally:
        daemon = abc.daemons.pop(mid)
        daemon.proc.kill()  # SIGKILL ends a frozen process too
        daemon.proc.wait(START_TIMEOUT_S)


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "frozen"])
def test_a_machine_that_dies_leaves_the_list_within_about_a_second(
    abc: Site, doomed: str, how: signal.Signals
) -> None:
    watch = watch_cli(abc, 60.0)
    try:
        lines = Lines(watch)
        _, listing = lines.wait_for("[")
        assert doomed in [row["id"] for row in json.loads(listing)]
        with abc.rider(None, timeout=2.0) as r:
            changes = r.follow_machines(timeout=0.2)
            wait_tokens(changes, {doomed: True}, START_TIMEOUT_S)
            killed_at = time.monotonic()
            abc.daemons[doomed].proc.send_signal(how)
            gone_at = wait_tokens(changes, {doomed: False}, GONE_BOUND_S)[doomed]
            cli_at, line = lines.wait_for(f'"id": "{doomed}"', GONE_BOUND_S)
            listed = [m.id for m in r.machines()]
        event = json.loads(line)
        assert event["alive"] is False
        assert doomed not in listed
        assert listed == ["a", "b", "c"]
        print(
            f"\n{how.name}: machine gone from follow_machines after"
            f" {(gone_at - killed_at) * 1000:.0f} ms, from `rider machines --watch` after"
            f" {(cli_at - killed_at) * 1000:.0f} ms"
        )
        assert gone_at - killed_at < GONE_BOUND_S
        watch.send_signal(signal.SIGINT)  # Ctrl-C ends the watch cleanly
        assert lines.rest() == [], "no other machine came or went"
        assert watch.wait(START_TIMEOUT_S) == 0
    finally:
        if watch.poll() is None:
            watch.kill()
        watch.wait(START_TIMEOUT_S)


def test_a_machine_arriving_is_followed_live(abc: Site) -> None:
    watch = watch_cli(abc, 60.0)
    mid = "late"
    try:
        lines = Lines(watch)
        _, listing = lines.wait_for("[")
        assert mid not in [row["id"] for row in json.loads(listing)]
        abc.add_daemon(mid, "peer")
        _, line = lines.wait_for(f'"id": "{mid}"', START_TIMEOUT_S)
        assert json.loads(line)["alive"] is True
        abc.daemons[mid].stop()
        _, line = lines.wait_for(f'"id": "{mid}"', GONE_BOUND_S)
        assert json.loads(line)["alive"] is False
    finally:
        abc.daemons.pop(mid).stop(signal.SIGKILL)
        watch.kill()
        watch.wait(START_TIMEOUT_S)
