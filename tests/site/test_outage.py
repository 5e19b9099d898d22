"""The site router dies mid-session and comes back; and a router that is not there at all.

Machine x is a peer (the shipped zenoh.json5, listening on its own loopback port), machine y a
client of the router; each runs a session started by its own client Rider. When the router is
SIGKILLed the Riders' tokens vanish for the machines, which pause with their relays off; a local
Rider connected straight to x watches that happen. When the router is back on the same port,
everyone reconnects by themselves, the paused sessions wait for Resume, and a Resume sent during
the outage and retried with the same transaction id afterwards acts exactly once.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from ride_machine.rider.client import MachineTimeout, Rider
from ride_machine.schema.commands import (
    Command,
    CommandRequest,
    Direction,
    ReplyCode,
    RotateStep,
    Session,
    TiltStep,
)
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import (
    STEP_TIMEOUT_S,
    prepare,
    relays_off,
    wait_cycles,
    wait_revolutions,
)
from tests.procs import REPO, START_TIMEOUT_S, free_port, machine_cmd, rider_cmd
from tests.site.stand import Site, run_cli, site, wait_tokens, write_doc_config

pytestmark = pytest.mark.integration

REVOLUTIONS = 6
SESSION = Session(
    name="outage",
    steps=[TiltStep(degrees=30.0), RotateStep(direction=Direction.CW, revolutions=REVOLUTIONS)],
)
REVOLUTION_SLACK = 0.1
LOSS_BOUND_S = 5.0
"""Generous bound for a machine to pause once the router is gone (measured, see report)."""
RECONNECT_BOUND_S = 15.0
"""Bound for everyone to find the restarted router (peer retry back-off is 1 s, then 2 s, ...)."""


@pytest.fixture
def xy(tmp_path: Path) -> Iterator[Site]:
    with site(tmp_path) as stand:
        stand.start_daemons({"x": "peer", "y": "client"})
        yield stand


def wait_status(rider: Rider, ok: Callable[[Status], bool], timeout: float) -> Status:
    """The first status (current or published) that satisfies `ok`."""
    deadline = time.monotonic() + timeout
    for update in rider.watch(("status",), timeout=timeout):
        if isinstance(update, Status) and ok(update):
            return update
        assert time.monotonic() < deadline, f"no such status in {timeout:g} s: {update}"
    raise AssertionError("status went quiet")


def local_rider(stand: Site, machine_id: str) -> Rider:
    """A Rider on the machine's own port, not through the router (an HMI next to it)."""
    daemon = stand.daemons[machine_id]
    return daemon.rider(supervise=False, timeout=2.0)


def start_sessions(riders: dict[str, Rider]) -> dict[str, SimWorldState]:
    """Each machine prepared, then riding `SESSION` past its first revolution; the worlds
    before the start."""
    with ThreadPoolExecutor(2) as pool:
        list(pool.map(prepare, riders.values()))
    before = {mid: r.sim("world") for mid, r in riders.items()}
    started = {mid: r.start(SESSION) for mid, r in riders.items()}
    for mid, r in riders.items():
        assert started[mid].code is ReplyCode.RESP_START_ACCEPTED
        wait_revolutions(r, started[mid], 1)
    return before


def outage_resumes(riders: dict[str, Rider]) -> dict[str, CommandRequest]:
    """One Resume request per machine, stamped now: sent during the outage, retried after."""
    return {
        mid: CommandRequest(
            transaction_id=f"outage-resume-{mid}", timecode=time.time(), rider=r.rider_id
        )
        for mid, r in riders.items()
    }


def resume_to_done_once(
    riders: dict[str, Rider],
    resumes: dict[str, CommandRequest],
    before: dict[str, SimWorldState],
) -> None:
    """The Resume sent during the outage, retried: each session finishes its revolutions, and
    the same request again is answered with the recorded reply."""
    for mid, r in riders.items():
        first = r.command(Command.RESUME, resumes[mid])
        assert first.code is ReplyCode.RESP_RESUMED, (mid, first)
        done = r.wait_for({MachineState.DONE}, STEP_TIMEOUT_S, after=first.timecode)
        assert done.session is not None
        assert done.session.revolutions_done == done.session.revolutions_total == REVOLUTIONS
        travelled = r.sim("world").revolutions - before[mid].revolutions
        assert travelled == pytest.approx(REVOLUTIONS, abs=REVOLUTION_SLACK), mid
        assert relays_off(r)
        # Once more with the same id: the recorded reply, not a second Resume (which DONE
        # would refuse).
        again = r.command(Command.RESUME, resumes[mid])
        assert again == first
        assert r.status().state is MachineState.DONE


@pytest.mark.hazard("H36")
def test_router_lost_mid_session_pauses_and_a_retried_resume_finishes_it_once(
    xy: Site,
) -> None:
    with (
        xy.rider("x", timeout=1.0) as cx,
        xy.rider("y", timeout=1.0) as cy,
        local_rider(xy, "x") as local,
    ):
        riders = {"x": cx, "y": cy}
        wait_tokens(local.follow_machines(0.2), {"x": True}, START_TIMEOUT_S)
        before = start_sessions(riders)

        killed_at = time.monotonic()
        xy.router.kill()
        paused = local.wait_for({MachineState.PAUSED}, LOSS_BOUND_S)
        noticed_s = time.monotonic() - killed_at
        assert paused.previous_state is MachineState.RUNNING
        assert not paused.rider_connected
        assert any("Rider lost" in w for w in paused.warnings), paused.warnings
        assert relays_off(local)
        held = local.sim("world")

        # Sent during the outage: no route, no reply, and it reaches no machine.
        resumes = outage_resumes(riders)
        for mid, r in riders.items():
            with pytest.raises(MachineTimeout):
                r.command(Command.RESUME, resumes[mid])
        wait_cycles(local, 30)
        still = local.sim("world")
        assert (still.revolutions, still.tilt_deg) == (held.revolutions, held.tilt_deg)
        assert not any(still.relays.values())

        restarted_at = time.monotonic()
        xy.router.start()
        wait_tokens(cx.follow_machines(0.2), {"x": True, "y": True}, RECONNECT_BOUND_S)
        listed_s = time.monotonic() - restarted_at
        for mid, r in riders.items():
            # The machine sees its Rider again; it stays paused until told otherwise.
            back = wait_status(r, lambda s: s.rider_connected, RECONNECT_BOUND_S)
            assert back.state is MachineState.PAUSED, (mid, back)
            assert back.previous_state is MachineState.RUNNING
            assert any("Rider lost" in w for w in back.warnings), (mid, back.warnings)
            assert back.session is not None and back.session.revolutions_done < REVOLUTIONS
            assert relays_off(r), mid
        print(
            f"\nrouter SIGKILL -> x PAUSED (seen locally) in {noticed_s * 1000:.0f} ms;"
            f" router process started -> x and y listed again in {listed_s * 1000:.0f} ms"
        )

        resume_to_done_once(riders, resumes, before)


@pytest.mark.hazard("H36")
def test_without_the_router_a_client_fails_clearly_and_a_client_daemon_exits(
    tmp_path: Path,
) -> None:
    client_conf = write_doc_config(tmp_path, "client")
    nowhere = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "daemon.log"
    with log.open("w") as out:
        daemon = subprocess.Popen(
            machine_cmd(
                *["run", "--sim", "--id", "lonely", "--data-dir", str(tmp_path / "data")],
                *["--zenoh-config", str(client_conf), "--connect", nowhere],
            ),
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=REPO,
        )
    try:
        rider = run_cli(
            rider_cmd("--connect", nowhere, "--zenoh-config", str(client_conf), "machines")
        )
        assert rider.returncode == 3, (rider.stdout, rider.stderr)
        assert "cannot open the Zenoh session" in rider.stderr
        assert "Traceback" not in rider.stderr
        assert daemon.wait(START_TIMEOUT_S) == 1
        assert "event=zenoh_open_failed" in log.read_text()
    finally:
        if daemon.poll() is None:
            daemon.kill()
        daemon.wait(START_TIMEOUT_S)
