"""`LoopPort`: the scan loop as every other thread sees it (the bus's Zenoh callbacks, its
reader threads, the fast-data server). Nothing else of the loop is theirs to read.

Commands run between two cycles under the loop's lock (`execute`); any other work is a task
for the scan thread (`submit`); what the loop published is immutable values read without the
lock (`published`, `moving`); a Rider's heartbeat is one write into the record the deadman reads
(`heartbeat`).
"""

from __future__ import annotations

from collections.abc import Callable

from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.completion import Completion
from ride_machine.schema.status import MotionRef
from ride_machine.service.core.commands.identity import Identity
from ride_machine.service.errors import Busy

from .inbox import Task
from .loop import ScanLoop
from .sink import Published


class LoopPort:
    """What another thread may ask of the scan loop; safe from any thread."""

    def __init__(self, loop: ScanLoop, clock: Callable[[], float]) -> None:
        """`clock`: the loop's clock (the runner's), read for commands run between cycles."""
        self._loop = loop
        self._clock = clock

    def execute(
        self,
        command: Command,
        request: CommandRequest,
        *,
        sender: str | None,
        timeout: float | None,
        identity: Identity | None = None,
    ) -> Reply | None:
        """Run a command now, on the calling thread under the loop's lock, between two cycles.

        The command sees the state the last cycle left, as a queued one would; its effect on
        outputs comes with the next cycle, which reads inputs and handles E-stop first. None
        while it cannot: before the first scan and after shutdown (`submit` it instead), and
        with `timeout=None` (never wait) while a cycle is in progress; a BUSY reply when the
        scan thread holds the lock longer than `timeout` (stalled). `sender`: the Rider the
        request names, as claimed; `identity`: the same once it confirmed the request
        (service/bus/confirm.py), for the history."""
        loop, clock = self._loop, self._clock
        if timeout is None:
            if not loop.lock.acquire(blocking=False):
                return None
        elif not loop.lock.acquire(timeout=timeout):
            return Reply.failure(
                Busy("scan loop not responding; retry later").to_error(),
                transaction_id=request.transaction_id,
                command=command.value,
                timecode=clock() + loop.wall_offset,
                request_timecode=request.timecode,
            )
        try:
            if loop.cycle == 0 or loop.inbox.closed:
                return None
            return loop.execute(command, request, clock(), sender=sender, identity=identity)
        finally:
            loop.lock.release()

    def wire(self, reply: Reply) -> bytes | None:
        """`reply` as the msgpack bytes made when it was recorded, if it is the reply recorded
        last (one serialisation per command); None: encode it afresh."""
        return self._loop.transactions.wire(reply)

    def submit(self, task: Task[ScanLoop]) -> bool:
        """Queue work for the scan thread (service/core/scan/tasks.py); False when the queue is
        full or the loop has stopped."""
        return self._loop.inbox.put(task)

    def published(self) -> Published:
        """The latest published records (status, calibration, IO, axes), as one value."""
        return self._loop.published

    def notice(self, transaction_id: str) -> Completion | MotionRef | None:
        """How a motion ended; the motion itself while it runs; None if unknown."""
        return self._loop.completions.lookup(transaction_id)

    def notices(self) -> list[Completion]:
        """Every remembered completion notice, oldest first."""
        return self._loop.completions.recent()

    def moving(self) -> bool:
        """Motion under way or resumable, as the latest cycle or command left it: a value the
        loop publishes, read without its lock (a Zenoh thread never waits on a cycle)."""
        return self._loop.moving

    def release_records(self, timeout: float) -> None:
        """Hand the event history what the loop holds for its next cycle (a history read then
        sees every command answered before it); skipped for a loop that holds its lock past
        `timeout` (stalled)."""
        loop = self._loop
        if loop.recorder.holding and loop.lock.acquire(timeout=timeout):
            try:
                loop.recorder.release()
            finally:
                loop.lock.release()

    def heartbeat(self, rider: str) -> None:
        """`rider`'s heartbeat arrived now, on the loop's clock: for the deadman to judge
        (nothing to record without the loop's heartbeat record: an in-process rig)."""
        beats = self._loop.beats
        if beats is not None:
            beats.beat(rider, self._clock())

    def rider_gone(self, rider: str) -> None:
        """`rider`'s token went: its heartbeats are history."""
        beats = self._loop.beats
        if beats is not None:
            beats.forget(rider)

    def rider_back(self, rider: str) -> None:
        """`rider`'s token is there (again): its heartbeats count."""
        beats = self._loop.beats
        if beats is not None:
            beats.returned(rider)

    def cycle(self) -> int:
        """The number of the last scan cycle."""
        return self._loop.cycle
