"""Losing the controlling Rider mid-session: the machine pauses with its relays off.

A child Python process starts the session as the supervising Rider and is SIGKILLed; this test
(another Rider, one that never commands motion) watches the machine react.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import pytest

from ride_machine.schema.commands import ReplyCode
from ride_machine.schema.status import MachineState, Status
from tests.integration import rider_proc
from tests.integration.support import (
    STEP_TIMEOUT_S,
    module_machine,
    prepare,
    relays_off,
    wait_revolutions,
)
from tests.procs import REPO, Daemon, rider_cmd

pytestmark = pytest.mark.integration

LONG_SESSION = ("--revolutions", "40", "prepare", "start", "running", "hold")
"""20 s of motion at the fast config: still running whenever the test gets to act."""

LOSS_BOUND_S = 5.0
"""Upper bound the test waits for the pause: the lease in the test config is 1 s, Zenoh's
default lease (a Rider without --zenoh-config) 10 s, the heartbeat timeout 0.5 s."""


machine = module_machine("rider-loss")


def rider_process(daemon: Daemon, *steps: str) -> subprocess.Popen[str]:
    cmd = rider_proc.command(daemon.endpoint, daemon.zenoh_config, daemon.machine_id, *steps)
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO)


@pytest.mark.hazard("H06")
def test_killing_the_rider_mid_session_pauses_with_relays_off(machine: Daemon) -> None:
    child = rider_process(machine, *LONG_SESSION)
    try:
        started = rider_proc.read_step(child, "start")
        assert started["reply"]["code"] == ReplyCode.RESP_START_ACCEPTED
        held = rider_proc.read_step(child, "hold")
        with machine.rider() as observer:
            running = observer.status()
            assert running.state is MachineState.RUNNING
            assert running.rider_connected
            killed_at = time.monotonic()
            child.send_signal(signal.SIGKILL)
            child.wait(STEP_TIMEOUT_S)
            paused = observer.wait_for({MachineState.PAUSED}, LOSS_BOUND_S)
            noticed_s = time.monotonic() - killed_at
            print(
                f"rider loss: killed -> PAUSED seen by another Rider in {noticed_s * 1000:.0f} ms"
            )

            assert paused.previous_state is MachineState.RUNNING
            assert not paused.rider_connected
            assert any("Rider lost" in w for w in paused.warnings), paused.warnings
            assert relays_off(observer)
            assert machine.has_logged(f"rider={held['rider']}")

            # Another Rider may take over: the paused session resumes where it was.
            assert paused.session is not None
            reply = observer.resume()
            assert reply.code is ReplyCode.RESP_RESUMED
            wait_revolutions(observer, reply, paused.session.revolutions_done + 1)
            reply = observer.stop()
            assert observer.wait_for({MachineState.DONE}, STEP_TIMEOUT_S, after=reply.timecode)
    finally:
        if child.poll() is None:
            child.kill()
        child.wait(STEP_TIMEOUT_S)


def test_a_reading_rider_that_leaves_changes_nothing(machine: Daemon) -> None:
    child = rider_process(machine, *LONG_SESSION)
    try:
        rider_proc.read_step(child, "hold")
        with machine.rider() as observer:
            # A one-shot reader (the CLI's `rider status`) supervises nothing: it comes and goes.
            with machine.rider(supervise=False) as reader:
                before = reader.status()
            assert before.state is MachineState.RUNNING and before.session is not None
            goal = before.session.revolutions_done + 2
            states = []
            for update in observer.watch(("status",), timeout=STEP_TIMEOUT_S):
                assert isinstance(update, Status)
                states.append(update.state)
                if update.session is not None and update.session.revolutions_done >= goal:
                    break
            assert set(states) == {MachineState.RUNNING}, states
            reply = observer.stop()
            assert observer.wait_for({MachineState.DONE}, STEP_TIMEOUT_S, after=reply.timecode)
    finally:
        child.kill()
        child.wait(STEP_TIMEOUT_S)


@pytest.mark.hazard("H07")
def test_a_frozen_cli_rider_on_zenoh_defaults_pauses_the_ride_by_its_heartbeat(
    machine: Daemon, tmp_path: Path
) -> None:
    """Reproduction 2 of issue 15: `rider start --wait` as the README shows it (no
    --zenoh-config, so Zenoh's 10 s lease), SIGSTOPped mid-session. Its liveliness token stays
    alive for the lease; its heartbeat stops at once, and the machine pauses on that."""
    session = tmp_path / "long.json"
    session.write_text(
        json.dumps(
            {
                "name": "long",
                "steps": [{"kind": "tilt", "degrees": 45}, {"kind": "rotate", "revolutions": 40}],
            }
        )
    )
    with machine.rider() as observer:
        prepare(observer)
        observer.set_param("rider_loss.timeout_s", 0.5)  # the project default
        cmd = rider_cmd("--connect", machine.endpoint, "--machine", machine.machine_id)
        child = subprocess.Popen(
            [*cmd, "start", "--session", str(session), "--wait"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        try:
            for update in observer.watch(("status",), timeout=STEP_TIMEOUT_S):
                assert isinstance(update, Status)
                if update.state is MachineState.RUNNING and update.rider_connected:
                    break
            stopped_at = time.monotonic()
            child.send_signal(signal.SIGSTOP)
            paused = observer.wait_for({MachineState.PAUSED}, LOSS_BOUND_S)
            noticed_s = time.monotonic() - stopped_at
            print(
                f"rider loss: SIGSTOP -> PAUSED seen by another Rider in {noticed_s * 1000:.0f} ms"
            )
            assert paused.previous_state is MachineState.RUNNING
            assert not paused.rider_connected  # the token is still alive: the heartbeat decided
            assert relays_off(observer)
            assert machine.has_logged("cause=heartbeat")
        finally:
            child.send_signal(signal.SIGKILL)
            child.wait(STEP_TIMEOUT_S)
            reply = observer.stop()
            observer.wait_for({MachineState.DONE}, STEP_TIMEOUT_S, after=reply.timecode)
            # Back to the file's (less strict) value once nothing moves (a safety setting).
            observer.reset_param("rider_loss.timeout_s")
