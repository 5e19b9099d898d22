"""`SignalThread`: a signal's handler runs on a thread of its own, so it never waits for a lock
held by the code the signal interrupted (a stream of SIGTERMs froze `machine run` so)."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator

import pytest

from ride_machine.service.signals import SignalThread

WAIT_S = 10.0


@pytest.fixture
def usr1() -> Iterator[None]:
    """SIGUSR1 back to what it was, whatever a test leaves behind."""
    before = signal.getsignal(signal.SIGUSR1)
    try:
        yield
    finally:
        signal.signal(signal.SIGUSR1, before)


def test_the_handler_runs_on_the_signal_thread_and_close_puts_the_old_handler_back(
    usr1: None,
) -> None:
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    got: list[tuple[int, str]] = []
    done = threading.Event()

    def handler(signum: int) -> None:
        got.append((signum, threading.current_thread().name))
        done.set()

    thread = SignalThread(handler, [signal.SIGUSR1])
    thread.start()
    os.kill(os.getpid(), signal.SIGUSR1)
    assert done.wait(WAIT_S)
    thread.close()
    assert got == [(signal.SIGUSR1, "signals")]
    assert signal.getsignal(signal.SIGUSR1) is signal.SIG_IGN
    assert signal.set_wakeup_fd(-1) == -1  # the wake-up pipe is gone with it


def test_a_lock_the_interrupted_thread_holds_is_only_waited_for(usr1: None) -> None:
    """The main thread holds a plain lock when the signal comes; a handler that takes it
    waits until the main thread lets go, where a handler on the main thread never got it."""
    lock = threading.Lock()
    waiting, handled = threading.Event(), threading.Event()
    took: list[bool] = []

    def handler(signum: int) -> None:
        waiting.set()
        took.append(lock.acquire(timeout=WAIT_S))  # on the main thread: False, after 10 s
        lock.release()
        handled.set()

    thread = SignalThread(handler, [signal.SIGUSR1])
    thread.start()
    try:
        with lock:
            os.kill(os.getpid(), signal.SIGUSR1)
            assert waiting.wait(WAIT_S)
        assert handled.wait(WAIT_S)
    finally:
        thread.close()
    assert took == [True]


def test_close_can_leave_the_signals_ignored(usr1: None) -> None:
    """As a process that has stopped does: one more signal must not kill it before its last
    log lines are out."""
    signal.signal(signal.SIGUSR1, signal.SIG_DFL)
    thread = SignalThread(lambda signum: None, [signal.SIGUSR1])
    thread.start()
    thread.close(then=signal.SIG_IGN)
    assert signal.getsignal(signal.SIGUSR1) is signal.SIG_IGN
    os.kill(os.getpid(), signal.SIGUSR1)  # ignored: the test process lives on


def test_a_handler_that_fails_does_not_end_the_thread(
    usr1: None, caplog: pytest.LogCaptureFixture
) -> None:
    calls: list[int] = []
    first, second = threading.Event(), threading.Event()

    def handler(signum: int) -> None:
        calls.append(signum)
        if not first.is_set():
            first.set()
            raise RuntimeError("the first one fails")
        second.set()

    thread = SignalThread(handler, [signal.SIGUSR1])
    thread.start()
    try:
        os.kill(os.getpid(), signal.SIGUSR1)
        assert first.wait(WAIT_S)
        os.kill(os.getpid(), signal.SIGUSR1)
        assert second.wait(WAIT_S)
    finally:
        thread.close()
    assert calls == [signal.SIGUSR1, signal.SIGUSR1]
    assert any("event=signal_handler_failed" in r.getMessage() for r in caplog.records)
