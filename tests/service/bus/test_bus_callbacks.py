"""Direct callbacks keep a Python thread state on Zenoh's threads between calls.

A child process (Zenoh's runtime and its threads are per process) opens two real sessions
linked over loopback: the queries cross the link, so the queryable's callback runs on a thread
of Zenoh's, which Python did not start. A `threading.local` lives in the thread state: a
count it keeps from one call to the next shows the state was kept; a thread state built for
each call starts it afresh every time.
"""

from __future__ import annotations

import json
import os
import sys
import threading
from collections.abc import Callable
from typing import Any

import pytest
import zenoh

from ride_machine.common import threadstate
from ride_machine.common.runtime import RUNTIME_ENV, use_runtime
from ride_machine.common.zenoh_session import open_session
from ride_machine.rider.client import _direct as riders_direct
from ride_machine.service.bus.callbacks import direct
from tests.procs import free_port, run_bounded

KEY = "test/callbacks/echo"
CALLS = 12
Counts = dict[str, list[int]]
"""Per thread that ran the callback: the per-thread count each call saw."""


def _config(kind: str, endpoint: str) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5(f"{kind}/endpoints", f'["{endpoint}"]')
    return conf


def _counting(counts: Counts) -> Callable[[zenoh.Query], None]:
    local = threading.local()
    python_threads = {t.ident for t in threading.enumerate()}

    def fn(query: zenoh.Query) -> None:
        local.count = getattr(local, "count", 0) + 1
        ident = threading.get_ident()
        assert ident not in python_threads, "ran on a thread Python started"
        counts.setdefault(str(ident), []).append(local.count)
        query.reply(query.key_expr, b"ok")

    return fn


def scenario(how: str, threads: int) -> Counts:
    """Serve `CALLS` queries with the callback wrapped `how`; the counts it saw."""
    use_runtime(threads)
    if how == "bounded":  # the bound reached before the first call
        threadstate.KEPT_MAX = 0
    counts: Counts = {}
    fn = _counting(counts)
    if how == "pyo3":
        handler: zenoh.handlers.Callback[Any] = zenoh.handlers.Callback(fn, indirect=False)
    else:
        handler = riders_direct(fn) if how == "rider" else direct(fn)  # type: ignore[arg-type]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(_config("listen", endpoint)) as server:
        queryable = server.declare_queryable(KEY, handler)
        with open_session(_config("connect", endpoint)) as client:
            for _ in range(200):  # the link's routes settle within a few tries
                if list(client.get(KEY, timeout=2.0)):
                    break
            for _ in range(CALLS):
                assert len(list(client.get(KEY, timeout=2.0))) == 1
        queryable.undeclare()
    assert sum(map(len, counts.values())) > CALLS
    return counts


def run_child(how: str, threads: int = 1) -> Counts:
    environ = {k: v for k, v in os.environ.items() if k != RUNTIME_ENV}
    child = [sys.executable, "-m", "tests.service.bus.test_bus_callbacks", how, str(threads)]
    proc = run_bounded(child, timeout=60, env=environ)
    assert proc.returncode == 0, proc.stderr
    counts: Counts = json.loads(proc.stdout.splitlines()[-1])
    return counts


@pytest.mark.parametrize(
    ("how", "threads"),
    [("direct", 1), ("direct", 0), ("rider", 0)],
    ids=["the daemon, one Zenoh thread", "the daemon, Zenoh's own threads", "the Rider"],
)
def test_a_direct_callback_keeps_its_thread_state_from_one_call_to_the_next(
    how: str, threads: int
) -> None:
    counts = run_child(how, threads)
    # Per Zenoh thread the count goes on (1, 2, 3, ...): one state for every call.
    assert all(c == list(range(1, len(c) + 1)) for c in counts.values()), counts
    assert max(map(len, counts.values())) > CALLS // 2


def test_pyo3s_own_direct_callback_builds_a_thread_state_per_call() -> None:
    """What `direct` is for: without it, every call starts on a fresh thread state."""
    counts = run_child("pyo3")
    assert all(set(c) == {1} for c in counts.values()), counts


def test_past_the_bound_a_new_thread_gets_pyo3s_default_again() -> None:
    """A pool whose threads come and go must not leak a state per thread for ever."""
    counts = run_child("bounded")
    assert all(set(c) == {1} for c in counts.values()), counts


if __name__ == "__main__":
    print(json.dumps(scenario(sys.argv[1], int(sys.argv[2]))))
