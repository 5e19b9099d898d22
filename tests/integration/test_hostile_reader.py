"""A peer that asks and stops reading: the machine's Zenoh thread is not its to hold.

Since Zenoh 1.8 a reply takes the asker's QoS, and a `get` blocks by default. A peer that sends
thousands of queries and never reads their replies (its handler full: an application stuck in
a callback, or a hostile one) fills its link's queue, and the daemon's next reply to it waits
for room on the Zenoh thread that also runs every other station's commands and the deadman's
heartbeats. With Zenoh's default (5 s) another station's command timed out (4.5 s) and a ride's
deadman (0.5 s) lost its controlling Rider; the configs now cut such a link after 0.25 s
(common/zenoh_session.py, BLOCK_WAIT_US).
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from ride_machine.schema.status import MachineState, Status
from tests.integration import rider_proc
from tests.integration.support import STEP_TIMEOUT_S, module_machine
from tests.procs import Daemon, LineReader, stop_process

pytestmark = pytest.mark.integration

QUERIES = 20_000
"""Status reads the peer sends and never reads: megabytes of replies, more than the socket
buffers on both sides hold."""
WATCH_S = 3.0
"""How long the other stations are watched once the peer has asked (the stall came at once)."""
ANSWER_BOUND_S = 1.5
"""The slowest command the other station may see: the peer's link is cut after 0.25 s; the
rest is a loaded host's margin, below the Rider's own 2 s timeout."""

HOSTILE = """
import sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", '["%s"]')
conf.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(conf)
# Handlers of one place each, never read: Zenoh's receive side stops at the second sample.
sub = session.declare_subscriber("%s/**", zenoh.handlers.FifoChannel(1))
asked = [
    session.get("%s/status", handler=zenoh.handlers.FifoChannel(1)) for _ in range(%d)
]
print("asked", flush=True)
time.sleep(120)
"""

machine = module_machine("hostile-reader")


@pytest.mark.hazard("H30")
def test_a_peer_that_asks_and_never_reads_holds_no_other_stations_command_or_ride(
    machine: Daemon,
) -> None:
    base = f"machine/{machine.machine_id}"
    script = HOSTILE % (machine.endpoint, base, base, QUERIES)
    with rider_proc.supervising(machine) as (_, _rider), machine.rider() as observer:
        assert observer.status().state is MachineState.RUNNING
        peer = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
        try:
            assert peer.stdout is not None
            assert LineReader(peer.stdout).line(STEP_TIMEOUT_S) == "asked"
            slowest, states = 0.0, set()
            deadline = time.monotonic() + WATCH_S
            while time.monotonic() < deadline:
                started = time.monotonic()
                observer.check_home()  # answered, or a MachineTimeout fails the test
                slowest = max(slowest, time.monotonic() - started)
                states.add(observer.status().state)
                time.sleep(0.02)
        finally:
            stop_process(peer)
        print(f"hostile reader: slowest command {slowest * 1000:.0f} ms, states {states}")
        assert slowest < ANSWER_BOUND_S
        # The supervising Rider's heartbeats got through: its ride was never paused.
        assert states == {MachineState.RUNNING}, states
        assert "rider_lost" not in machine.log()
        stopped = observer.stop()
        done = observer.wait_for({MachineState.DONE}, STEP_TIMEOUT_S, after=stopped.timecode)
        assert isinstance(done, Status)
