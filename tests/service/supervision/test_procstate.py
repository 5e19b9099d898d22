"""Where a frozen daemon's threads were (service/supervision/procstate.py), read from the
kernel for real: a thread blocked on a lock, a process stopped by SIGSTOP, one that is gone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

from ride_machine.service.supervision.procstate import describe, threads
from ride_machine.service.threads import NamedThread


def test_a_thread_blocked_on_a_lock_sleeps_in_a_futex_and_does_not_run() -> None:
    lock = threading.Lock()
    lock.acquire()
    blocked = NamedThread(target=lock.acquire, name="blocked", daemon=True)
    blocked.start()
    try:
        deadline = time.monotonic() + 10.0
        while True:  # bounded: until the kernel shows it asleep
            mine = {t.name: t for t in threads(os.getpid())}
            if mine.get("blocked") and mine["blocked"].state == "S":
                break
            assert time.monotonic() < deadline, mine
            time.sleep(0.01)
        first = threads(os.getpid())
        time.sleep(0.05)
        line = describe(threads(os.getpid()), first)
    finally:
        lock.release()
        blocked.join(5.0)
    entry = next(p for p in line.split("; ") if p.startswith("blocked:"))
    assert entry.startswith("blocked:S:futex"), entry
    assert "ran=+0ms" in entry, entry


def test_a_stopped_process_shows_every_thread_stopped_and_a_gone_one_nothing() -> None:
    code = "import threading, time; threading.Thread(target=time.sleep, args=(60,)).start()"
    code += "; time.sleep(60)"
    proc = subprocess.Popen([sys.executable, "-c", code])
    try:
        deadline = time.monotonic() + 10.0
        while len(threads(proc.pid)) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        proc.send_signal(signal.SIGSTOP)
        while {t.state for t in threads(proc.pid)} != {"T"}:
            assert time.monotonic() < deadline, threads(proc.pid)
            time.sleep(0.01)
        assert describe(threads(proc.pid)).count(":T") == len(threads(proc.pid))
    finally:
        proc.kill()
        proc.wait(10.0)
    assert threads(proc.pid) == []
    assert describe([]) == "gone"
