"""`bench.common.thread_cpu`: a process's CPU by thread, under the names the daemon gives them."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from bench.common import HISTORY, children, cpu_seconds, rss_bytes, thread_cpu
from ride_machine.service.threads import NamedThread

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def test_a_named_thread_is_counted_under_its_name_and_the_main_thread_as_main() -> None:
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            sum(range(1000))

    worker = NamedThread(target=spin, name="cpu-probe")
    before = thread_cpu(os.getpid())
    worker.start()
    try:
        end = time.thread_time() + 0.05  # the main thread's own CPU, too
        while time.thread_time() < end:
            pass
        after = thread_cpu(os.getpid())
    finally:
        stop.set()
        worker.join(5.0)
    assert "cpu-probe" not in before
    assert after["cpu-probe"] > 0.0
    assert after["main"] - before["main"] >= 0.05


def test_a_child_process_counts_as_history_and_with_the_family() -> None:
    """A daemon's history process (`[events] process`): its CPU and memory are the daemon's
    too in the benchmarks (`family=True`), and its threads one column of `thread_cpu`."""
    spin = "import time\nend = time.process_time() + 0.1\nwhile time.process_time() < end: pass\n"
    child = subprocess.Popen(
        [sys.executable, "-c", spin + "import sys; sys.stdin.read()"], stdin=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and thread_cpu(os.getpid()).get(HISTORY, 0.0) < 0.1:
            child.poll()  # bounded: the child spins its 0.1 s of CPU, then waits on stdin
        assert thread_cpu(os.getpid())[HISTORY] >= 0.1
        assert cpu_seconds(os.getpid(), family=True) - cpu_seconds(os.getpid()) >= 0.05  # in ticks
        assert rss_bytes(os.getpid(), family=True) > rss_bytes(os.getpid())
        assert children(os.getpid()) == [child.pid]
    finally:
        child.kill()
        child.wait()
