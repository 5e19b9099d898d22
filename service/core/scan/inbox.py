"""The scan thread's inbox: work other threads hand it (`Task`), and the wake-up that comes with it.

`Inbox.put` from any thread queues a task and wakes the runner early, so a reply is prompt; the
scan thread takes a bounded number between and within cycles (`ScanLoop.service_inbox`). The
inbox knows nothing of the loop a task runs with: it is the type parameter (`Inbox[ScanLoop]`),
so this module sits below the loop and the tasks (service/core/scan/tasks.py) above it.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Generic, Protocol, TypeVar

from ride_machine.schema.errors import Error

L = TypeVar("L")
"""What the inbox's tasks run with (the scan loop)."""
L_contra = TypeVar("L_contra", contravariant=True)


class Task(Protocol[L_contra]):
    """Work for the scan thread: `run` there with the loop, or `reject` if it can never run."""

    def run(self, loop: L_contra, now: float) -> None: ...

    def reject(self, error: Error) -> None: ...


class Wake:
    """`threading.Event`'s set/clear/wait on one raw lock, released while set.

    The runner waits on it every cycle: a wait is one lock acquire, where `Event.wait` builds
    a `Condition` waiter each time (~40 µs of a cold cycle on a 2-core host, bench.cost).
    """

    def __init__(self) -> None:
        self._gate = threading.Lock()
        self._gate.acquire()  # held while clear: a wait blocks on it
        self._guard = threading.Lock()
        self.flag = False
        """`is_set()` as a plain attribute, for the scan loop's every cycle (no call)."""

    def is_set(self) -> bool:
        return self.flag

    def set(self) -> None:
        with self._guard:
            if not self.flag:
                self.flag = True
                self._gate.release()

    def clear(self) -> None:
        with self._guard:
            if self.flag:
                self.flag = False
                self._gate.acquire()  # a waiter passing through releases it at once

    def wait(self, timeout: float) -> bool:
        """True once set (it stays set), False after `timeout` seconds."""
        if not self._gate.acquire(True, timeout):
            return False
        self._gate.release()
        return True


class Inbox(Generic[L]):
    """Thread-safe queue into the scan thread; `put` wakes the runner so replies are prompt."""

    def __init__(self, capacity: int = 1024) -> None:
        self.capacity = capacity
        self._items: deque[Task[L]] = deque()
        self._lock = threading.Lock()
        self.wake = Wake()
        self.closed = False

    def put(self, task: Task[L]) -> bool:
        """Queue a task; False (and nothing queued) when full or closed."""
        with self._lock:
            if self.closed or len(self._items) >= self.capacity:
                return False
            self._items.append(task)
        self.wake.set()
        return True

    def take(self, limit: int) -> list[Task[L]]:
        if not self._items and not self.wake.flag:
            return []  # the common case, every cycle: no lock
        with self._lock:
            n = min(limit, len(self._items))
            out = [self._items.popleft() for _ in range(n)]
            if not self._items:
                self.wake.clear()
        return out

    def close(self) -> list[Task[L]]:
        """Refuse further tasks and hand back the ones never run."""
        with self._lock:
            self.closed = True
            out = list(self._items)
            self._items.clear()
        return out

    def __len__(self) -> int:
        return len(self._items)
