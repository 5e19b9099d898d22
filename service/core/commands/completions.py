"""The machine's memory of completion notices: the recent ones by transaction id, and the
motion still under way, readable from the bus thread (a late Rider asks how its command ended).

A notice is answered only once the status its motion ended with is the published one (what a
status query answers), just before the two are published: a command serviced between two
cycles (a Stop) ends a motion at once, and a Rider that got the notice then and asked for the
status found the one before it (FAULT_ESTOP after "STOPPED"); a Rider that heard that status
and asked for the notice at once is not told the motion is under way.

Each notice is kept as its msgpack bytes, as `TransactionLog` keeps replies: a full window of
4,096 held 6.1 MiB as models and 1.5 MiB as bytes (a riding daemon filled it at ~3,000 motion
commands an hour, most of its growth in bench.rss_soak's rides); a read decodes it again."""

from __future__ import annotations

import threading
from collections import OrderedDict

from ride_machine.schema.codec import Format, decode, encode
from ride_machine.schema.completion import Completion
from ride_machine.schema.status import MotionRef


class CompletionLog:
    """The last `capacity` notices by transaction id (oldest forgotten first); thread-safe."""

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self._lock = threading.Lock()
        self._notices: OrderedDict[str, bytes] = OrderedDict()
        """Each notice's msgpack bytes by transaction id, oldest first."""
        self._active: MotionRef | None = None
        self._held: dict[str, MotionRef] = {}
        """Motions that ended, whose notices wait for their status: still under way here."""

    def hold(self, notice: Completion) -> None:
        """`notice` is taken but not yet published: its motion is answered as under way until
        `record`."""
        ref = MotionRef(
            transaction_id=notice.transaction_id,
            command=notice.command,
            started_at=notice.started_at,
        )
        with self._lock:
            self._held[notice.transaction_id] = ref
            if self._active is not None and self._active.transaction_id == notice.transaction_id:
                self._active = None

    def record(self, notice: Completion) -> None:
        packed = encode(notice, Format.MSGPACK)
        with self._lock:
            self._notices[notice.transaction_id] = packed
            self._notices.move_to_end(notice.transaction_id)
            self._held.pop(notice.transaction_id, None)
            if len(self._notices) > self.capacity:
                self._notices.popitem(last=False)
            if self._active is not None and self._active.transaction_id == notice.transaction_id:
                self._active = None

    def set_active(self, motion: MotionRef | None) -> None:
        """The motion whose notice is still due (None: no motion under way)."""
        with self._lock:
            self._active = motion

    def lookup(self, transaction_id: str) -> Completion | MotionRef | None:
        """The notice; the motion itself while it has not ended, or while its notice waits for
        its status; None if unknown (never a motion, forgotten, or from before the daemon
        started)."""
        with self._lock:
            packed = self._notices.get(transaction_id)
            held = self._held.get(transaction_id)
            active = self._active
        if packed is not None:  # decoded outside the lock: the scan thread records under it
            return _notice(packed)
        if held is not None:
            return held
        if active is not None and active.transaction_id == transaction_id:
            return active
        return None

    def recent(self) -> list[Completion]:
        """Every remembered notice, oldest first."""
        with self._lock:
            kept = list(self._notices.values())
        return [_notice(packed) for packed in kept]

    def __len__(self) -> int:
        return len(self._notices)


def _notice(packed: bytes) -> Completion:
    return decode(Completion, packed, Format.MSGPACK, limit=len(packed))
