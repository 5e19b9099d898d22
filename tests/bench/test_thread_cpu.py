"""`bench.common.thread_cpu`: a process's CPU by thread, under the names the daemon gives them."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest

from bench.common import thread_cpu
from service.threads import NamedThread

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
