"""`bus.zenoh_threads`: Zenoh's runtimes laid out as the daemon starts (read from outside, in
/proc), the operator's `ZENOH_RUNTIME` kept, and one Zenoh cannot read refused with its name."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from ride_machine.common.runtime import RUNTIME_ENV, runtime_layout
from ride_machine.service.config.model import BusSection
from ride_machine.service.supervision.outcome import EXIT_FAILED
from tests.procs import REPO, free_port, running_daemon, start_daemon

CHILD = """
import os, sys
import zenoh
from ride_machine.common.runtime import use_runtime
from ride_machine.common.zenoh_session import open_session
applied = use_runtime(int(sys.argv[1]))
def config(**endpoints):
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    for kind, endpoint in endpoints.items():
        conf.insert_json5(f"{kind}/endpoints", f'["{endpoint}"]')
    return conf
server = open_session(config(listen=sys.argv[2]))
answer = server.declare_queryable("t/q", lambda query: query.reply("t/q", b"ok"))
client = open_session(config(connect=sys.argv[2]))
for _ in range(100):  # a link, a query and its reply: every runtime that serves them is up
    replies = list(client.get("t/q", timeout=0.2))
    if replies and replies[0].ok is not None:
        break
tasks = os.listdir("/proc/self/task")
names = sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in tasks)
print(applied, os.environ.get("ZENOH_RUNTIME"), bool(replies), " ".join(names), sep="\\n")
client.close()
server.close()
"""

ZENOH_RUNTIMES = re.compile(r"^(rx|tx|net|acc|app)-\d+$")


def runtimes(names: list[str]) -> set[str]:
    """The Zenoh runtimes that have threads (`rx-0`, `rx-1`, `app-0` → rx, app); tokio names its
    blocking threads as its workers, so a count of them says nothing."""
    return {n.split("-")[0] for n in names if ZENOH_RUNTIMES.match(n)}


def run_child(code: str, args: list[str], env: dict[str, str] | None) -> list[str]:
    """`python -c code *args` with no `ZENOH_RUNTIME` but `env`'s: its stdout lines, the third
    of which says whether a query got its reply (checked here)."""
    environ = {k: v for k, v in os.environ.items() if k != RUNTIME_ENV}
    proc = subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
        env={**environ, **(env or {})},
    )
    lines = proc.stdout.splitlines()
    assert lines[2] == "True", proc.stderr
    return lines


def child(threads: int, env: dict[str, str] | None = None) -> tuple[str, str, list[str]]:
    """A process that lays out the runtime for `threads` and opens a session: what it applied,
    the `ZENOH_RUNTIME` it ran with, and its threads' names."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    applied, layout, _, names = run_child(CHILD, [str(threads), endpoint], env)
    return applied, layout, names.split()


def test_one_zenoh_thread_runs_every_runtime() -> None:
    applied, layout, names = child(1)
    assert applied == "zenoh_threads=1"
    assert layout == runtime_layout(1)
    assert runtimes(names) == {"app"}
    assert "app-0" in names


def test_zero_keeps_zenohs_own_layout() -> None:
    applied, layout, names = child(0)
    assert (applied, layout) == ("None", "None")
    # Zenoh's own receive and transmit runtimes served the round trip (a thread of each has run
    # and named itself); not `rx-1`, which a loaded host may not have run yet (run 41).
    assert {"rx", "tx"} <= runtimes(names)


def test_the_operators_zenoh_runtime_wins_and_is_named() -> None:
    mine = "(rx: (handover: app))"
    applied, layout, names = child(1, {RUNTIME_ENV: mine})
    assert applied == f"zenoh_runtime={RUNTIME_ENV}"
    assert layout == mine
    assert "rx" not in runtimes(names)
    assert "tx" in runtimes(names)  # not handed over by the operator's layout


def test_the_thread_count_is_checked() -> None:
    assert BusSection().zenoh_threads == 1
    assert BusSection(zenoh_threads=0).zenoh_threads == 0
    for bad in (-1, 65, "two"):
        with pytest.raises(ValidationError):
            BusSection(zenoh_threads=bad)


@pytest.mark.integration
def test_a_daemon_runs_zenoh_on_one_thread_and_says_so(tmp_path: Path) -> None:
    with running_daemon(tmp_path) as daemon:
        with daemon.rider(timeout=5.0) as rider:
            assert rider.check_home() is not None  # a query in, a reply out, on that thread
        names = [
            Path(f"/proc/{daemon.proc.pid}/task/{t}/comm").read_text().strip()
            for t in os.listdir(f"/proc/{daemon.proc.pid}/task")
        ]
        assert runtimes(names) == {"app"}
        assert daemon.has_logged("zenoh_threads=1")


@pytest.mark.integration
def test_a_zenoh_runtime_zenoh_cannot_read_stops_the_start_with_its_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Zenoh panics on it: the daemon says what was wrong, and where, and exits."""
    monkeypatch.setenv(RUNTIME_ENV, "(rx: (handover: app)")  # the closing parenthesis missing
    daemon = start_daemon(tmp_path, wait=False)
    try:
        assert daemon.proc.wait(60) == EXIT_FAILED
    finally:
        daemon.stop()
    log = daemon.log()
    assert "event=zenoh_open_failed" in log
    assert f"{RUNTIME_ENV}='(rx: (handover: app)' cannot be read by Zenoh" in log
    assert "PanicException" not in log
