"""`Deferred`: jobs run in order on a thread started for them, so whoever queues one never
waits for it (a Zenoh callback, the scan thread)."""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable

from ride_machine.service.threads import NamedThread

log = logging.getLogger(__name__)


class Deferred:
    """Jobs run in arrival order on a thread of their own (`name`), started when the first one
    arrives and ended when none is left (no thread while idle): commands that found the loop's
    lock taken; the replies the scan thread hands over (service/bus/outbox.py)."""

    def __init__(self, capacity: int, name: str = "cmd-deferred") -> None:
        self.capacity = capacity
        self.name = name
        self.pending = 0
        """Queued or running; the thread runs exactly while any is: while it does, a later
        job queues behind them (its order)."""
        self._jobs: deque[Callable[[], None]] = deque()
        self._lock = threading.Lock()
        self._idle = threading.Event()
        self._idle.set()

    def put(self, job: Callable[[], None]) -> bool:
        """Queue `job`; False (and nothing queued) when `capacity` are pending."""
        with self._lock:
            if self.pending >= self.capacity:
                return False
            self._jobs.append(job)
            self.pending += 1
            if self.pending > 1:
                return True  # the thread running the others takes it
            self._idle.clear()
        NamedThread(target=self._run, name=self.name, daemon=True).start()
        return True

    def drain(self, timeout: float) -> bool:
        """Wait until every job queued so far has run; False after `timeout`."""
        return self._idle.wait(timeout)

    def _run(self) -> None:
        while True:
            with self._lock:
                job = self._jobs.popleft()
            try:
                job()
            except Exception as exc:  # the next job must still run
                log.error("event=job_failed thread=%s error=%r", self.name, str(exc), exc_info=exc)
            with self._lock:
                self.pending -= 1
                if not self.pending:
                    self._idle.set()
                    return
