"""A Rider lays out Zenoh's runtime in its process as the daemon does (`zenoh_threads`, one
worker by default), read from outside in /proc; the variable it sets for that is gone after the
first open, so processes it starts later inherit nothing; the operator's `ZENOH_RUNTIME` wins,
and one Zenoh cannot read is a clear error."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from ride_machine.common import runtime
from ride_machine.common.runtime import RUNTIME_ENV, runtime_layout
from ride_machine.rider import cli
from ride_machine.rider.client import MachineTimeout, Rider
from tests.procs import REPO, free_port
from tests.service.supervision.test_zenoh_runtime import run_child, runtimes

CHILD = """
import os, subprocess, sys, time
import zenoh
from ride_machine.rider.client import Rider
threads, endpoint, first = int(sys.argv[1]), sys.argv[2], sys.argv[3]
def config():
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    return conf
server = zenoh.open(config()) if first == "other" else None
rider = Rider("m1", listen=[endpoint], zenoh_threads=threads, supervise=False).open()
during = os.environ.get("ZENOH_RUNTIME")
server = server or zenoh.open(config())
answer = server.declare_queryable("t/q", lambda query: query.reply("t/q", b"ok"))
for _ in range(100):  # a link, a query and its reply: every runtime that serves them is up
    replies = list(rider.session.get("t/q", timeout=0.2))
    if replies and replies[0].ok is not None:
        break
    time.sleep(0.05)  # the peer that connects first retries on its own period
tasks = os.listdir("/proc/self/task")
names = sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in tasks)
inherited = subprocess.run(
    [sys.executable, "-c", "import os; print(os.environ.get('ZENOH_RUNTIME'))"],
    capture_output=True, text=True, check=True,
).stdout.strip()
print(during, inherited, bool(replies), " ".join(names), sep="\\n")
rider.close()
server.close()
"""


def child(
    threads: int, env: dict[str, str] | None = None, first: str = "rider"
) -> tuple[str, str, list[str]]:
    """A process whose Rider opens with `threads` (after a session opened some other way when
    `first` is "other"): `ZENOH_RUNTIME` after the Rider's open, in a process it starts
    then, and its threads' names."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    after, inherited, _, names = run_child(CHILD, [str(threads), endpoint, first], env)
    return after, inherited, names.split()


def test_a_rider_runs_zenoh_on_one_thread_and_leaves_no_variable_behind() -> None:
    after, inherited, names = child(1)
    assert runtimes(names) == {"app"}
    assert "app-0" in names
    assert (after, inherited) == ("None", "None")


def test_zero_keeps_zenohs_own_layout() -> None:
    after, inherited, names = child(0)
    # The query and its reply ran through Zenoh's own receive and transmit runtimes, so a
    # thread of each has run and named itself; its other workers may not have yet on a loaded
    # host (run 41 read `rx-1` still under its creator's name), so they are not asked for.
    assert {"rx", "tx"} <= runtimes(names)
    assert (after, inherited) == ("None", "None")


def test_a_session_opened_before_keeps_its_layout() -> None:
    """The process's first session fixed the runtime (Zenoh's own here): the Rider changes
    nothing, and sets nothing."""
    after, inherited, names = child(1, first="other")
    assert {"rx", "tx"} <= runtimes(names)  # Zenoh's own runtimes, not one `app` thread
    assert (after, inherited) == ("None", "None")


def test_the_operators_zenoh_runtime_wins_and_stays() -> None:
    mine = "(rx: (handover: app))"
    after, inherited, names = child(1, {RUNTIME_ENV: mine})
    assert "rx" not in runtimes(names)
    assert "tx" in runtimes(names)  # not handed over by the operator's layout
    assert (after, inherited) == (mine, mine)
    assert runtime_layout(1) != mine


def test_the_cli_passes_its_thread_count_on(monkeypatch: pytest.MonkeyPatch) -> None:
    """`rider --zenoh-threads N` is the Rider's `zenoh_threads` (the session is not opened)."""
    seen: list[int] = []

    def opened(rider: Rider) -> Rider:
        seen.append(rider.zenoh_threads)
        raise MachineTimeout("not opened here")

    monkeypatch.setattr(Rider, "open", opened)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    for argv in (["--zenoh-threads", "0"], ["--zenoh-threads", "4"], []):
        code = cli.main(["--connect", endpoint, "-m", "m1", *argv, "status"])
        assert code == cli.EXIT_NO_REPLY
    assert seen == [0, 4, 1]


def test_a_zenoh_runtime_zenoh_cannot_read_is_a_usage_error_that_names_it() -> None:
    """Zenoh panics on it: the CLI says what was wrong, and exits 2, without a traceback."""
    broken = "(rx: (handover: app)"  # the closing parenthesis missing
    environ = {k: v for k, v in os.environ.items() if k != RUNTIME_ENV}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "ride_machine.rider.cli",
            "--connect",
            endpoint,
            "-m",
            "m1",
            "status",
        ],
        check=False,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        env={**environ, RUNTIME_ENV: broken},
    )
    assert proc.returncode == 2, proc.stderr
    assert f"{RUNTIME_ENV}={broken!r} cannot be read by Zenoh" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_only_the_first_open_waits_for_another() -> None:
    """A slow open (a router that does not answer) must not hold up every later one: once
    the layout is fixed, an open does not wait for the one under way."""
    started, release = threading.Event(), threading.Event()
    first = runtime._FirstOpen
    done = first.done
    first.done = True  # the layout is fixed (this process's first session has opened)
    try:

        def slow_open() -> None:
            with runtime.first_session_on(1):
                started.set()
                release.wait(5.0)

        slow = threading.Thread(target=slow_open)
        slow.start()
        assert started.wait(5.0)
        passed = threading.Event()

        def quick_open() -> None:
            with runtime.first_session_on(1) as applied:
                assert applied is None
                passed.set()

        quick = threading.Thread(target=quick_open)
        quick.start()
        assert passed.wait(5.0), "a later open waited for the slow one"
        release.set()
        slow.join(5.0)
        quick.join(5.0)
    finally:
        first.done = done
