"""At-most-once commands: a repeated `transaction_id` gets the first reply, nothing acts twice."""

from __future__ import annotations

from collections import OrderedDict

from ride_machine.schema.codec import Format, decode, encode
from ride_machine.schema.commands import Reply
from ride_machine.service.errors import DuplicateTransaction


class TransactionLog:
    """The last `capacity` replies by transaction id (oldest forgotten first).

    Each reply is kept as its msgpack bytes, the wire's usual format: the last one recorded
    goes out as those bytes (`wire`), so a command's reply is serialised once, not twice; a
    repeat reads them back. Kept as models, thousands of long-lived objects turning over at the
    command rate were the garbage collector's: a full collection every few thousand commands,
    15-18 ms with the GIL held (BENCHMARKS.md, section 1). Bytes are not tracked by it.
    """

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self._replies: OrderedDict[str, tuple[str, bytes]] = OrderedDict()
        self._last: tuple[Reply, bytes] | None = None
        self.repeats = 0

    def lookup(self, transaction_id: str, command: str, timecode: float) -> Reply | None:
        """The stored reply for a repeat, a refusal if the id was used for another command."""
        hit = self._replies.get(transaction_id)
        if hit is None:
            return None
        self.repeats += 1
        first_command, packed = hit
        reply = decode(Reply, packed, Format.MSGPACK, limit=len(packed))
        if first_command == command:
            return reply
        return Reply.failure(
            DuplicateTransaction(
                f"transaction_id {transaction_id!r} was already used for {first_command}",
                path="/transaction_id",
            ).to_error(),
            transaction_id=transaction_id,
            command=command,
            timecode=timecode,
            state=reply.state,
        )

    def record(self, transaction_id: str, command: str, reply: Reply) -> None:
        packed = encode(reply, Format.MSGPACK)
        self._replies[transaction_id] = (command, packed)
        self._last = (reply, packed)
        if len(self._replies) > self.capacity:
            self._replies.popitem(last=False)

    def remember(self, transaction_id: str, command: str, packed: bytes) -> None:
        """A reply given before this start (service/adapters/replay.py), as msgpack."""
        self._replies[transaction_id] = (command, packed)
        if len(self._replies) > self.capacity:
            self._replies.popitem(last=False)

    def wire(self, reply: Reply) -> bytes | None:
        """`reply` as msgpack, when it is the reply recorded last (`encode`'s bytes, made once);
        None for any other (a repeat's refusal, or a later command recorded meanwhile)."""
        last = self._last
        return last[1] if last is not None and last[0] is reply else None

    def __len__(self) -> int:
        return len(self._replies)
