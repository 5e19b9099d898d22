"""A Rider that says what it sees (issue 43, reproduction 6): `rider start --wait` through a link
that stalls, comes back, then is cut (a TCP proxy between the CLI and the machine).

The machine paused in 0.6 s when the link stalled, correctly; the CLI still showed RUNNING and
said nothing for 25 s of stall and 8 s of refused link, and would have waited its 600 s. Now it
says the machine is not answering within its timeout, says PAUSED (and why) once the link is
back, and exits 6 when the link stays down past `--link-limit`.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.schema.status import MachineState
from tests import linkproxy
from tests.integration.support import STEP_TIMEOUT_S, fast_daemon, prepare, states_over
from tests.procs import REPO, Daemon, LineReader, free_port, rider_cmd, stop_process

pytestmark = pytest.mark.integration

TIMEOUT_S = 2.0
LINK_LIMIT_S = 6.0
SLACK_S = 8.0
"""A process start, a status heartbeat and a loaded host, on top of what is waited for."""
RECONNECT_S = 20.0
"""Zenoh's own retry of a lost link (backing off) once the proxy moves again."""
LONG = {
    "name": "long",
    "steps": [{"kind": "tilt", "degrees": 45}, {"kind": "rotate", "revolutions": 60}],
}


@pytest.fixture
def proxy(tmp_path: Path) -> Iterator[tuple[Daemon, subprocess.Popen[str], int]]:
    """A fast daemon and a link proxy to it; both stopped whatever happens."""
    with fast_daemon(tmp_path) as daemon:
        port = free_port()
        link = linkproxy.start(port, daemon.endpoint.rsplit(":", 1)[1], STEP_TIMEOUT_S)
        try:
            yield daemon, link, port
        finally:
            os.kill(link.pid, signal.SIGCONT)
            stop_process(link, signal.SIGKILL)


def said(lines: LineReader, text: str, within: float) -> str:
    """The first stderr line with `text`, within `within` seconds (the earlier ones skipped)."""
    deadline = time.monotonic() + within
    while True:
        line = lines.line(timeout=max(0.1, deadline - time.monotonic()))
        assert line is not None, f"the waiting Rider ended before saying {text!r}"
        if text in line:
            return line


@pytest.mark.hazard("H08", "H36")
def test_wait_says_silence_then_paused_and_gives_up_when_the_link_stays_down(
    tmp_path: Path, proxy: tuple[Daemon, subprocess.Popen[str], int]
) -> None:
    daemon, link, port = proxy
    session = tmp_path / "long.json"
    session.write_text(json.dumps(LONG))
    with daemon.rider(supervise=False) as observer:
        prepare(observer)
        cmd = rider_cmd("--connect", f"tcp/127.0.0.1:{port}", "--zenoh-config")
        cmd += [str(daemon.zenoh_config), "--machine", "m1", "--timeout", f"{TIMEOUT_S:g}"]
        cmd += ["start", "--session", str(session), "--wait", "--link-limit", f"{LINK_LIMIT_S:g}"]
        waiting = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO
        )
        try:
            assert waiting.stderr is not None
            lines = LineReader(waiting.stderr)
            observer.wait_for({MachineState.RUNNING}, STEP_TIMEOUT_S)
            states_over(observer, 100)  # a second of RUNNING: the waiting Rider has heard it
            os.kill(link.pid, signal.SIGSTOP)  # the link stalls
            stalled = time.monotonic()
            quiet = said(lines, "not answering", TIMEOUT_S + SLACK_S)
            told_s = time.monotonic() - stalled
            paused = observer.wait_for({MachineState.PAUSED}, STEP_TIMEOUT_S)
            os.kill(link.pid, signal.SIGCONT)  # the link comes back
            again = said(lines, "answering again", RECONNECT_S + SLACK_S)
            why = said(lines, "machine PAUSED", SLACK_S)
            os.kill(link.pid, signal.SIGKILL)  # cut, and the port refuses from now on
            cut = time.monotonic()
            _, err = waiting.communicate(timeout=LINK_LIMIT_S + RECONNECT_S + SLACK_S)
            gave_up_s = time.monotonic() - cut
        finally:
            stop_process(waiting)
        observer.stop()
    assert told_s < TIMEOUT_S + SLACK_S, told_s
    assert "not answering" in quiet and "RUNNING" in quiet, quiet
    assert paused.previous_state is MachineState.RUNNING
    assert "PAUSED" in again, again
    assert "controlling Rider lost" in why, why
    assert waiting.returncode == 6, err
    assert "no word from machine m1" in err and "--link-limit 6" in err, err
    assert LINK_LIMIT_S - 1.0 < gave_up_s < LINK_LIMIT_S + SLACK_S, gave_up_s
