"""The command path: one request per command with a fresh transaction id, sent again with the
same id on a timeout (so a retry can never act twice), valid only while this Rider waits."""

from __future__ import annotations

import itertools
import time
import uuid
from typing import Any

from ride_machine.schema.codec import encode, pack
from ride_machine.schema.commands import VALID_FOR_MAX_S, Command, CommandRequest, Reply

from .errors import CommandRefused, MachineTimeout, RiderError
from .link import Link
from .machines import Machines
from .transport import Transport


class Commands:
    """Commands to this Rider's machine, and the transaction ids they carry."""

    def __init__(self, link: Link, machines: Machines, transport: Transport) -> None:
        self.link = link
        self.machines = machines
        self.transport = transport
        self.tag = uuid.uuid4().hex[:8]
        """This Rider's transaction ids are `<tag>-<counter>`."""
        self._ids = itertools.count(1)
        self._keys: dict[Command, str] = {}

    def new_transaction_id(self) -> str:
        return f"{self.tag}-{next(self._ids)}"

    def check_ids(self) -> None:
        """What `_own_request` packs without a model, checked once the Rider is open: a
        tag-and-counter id and this session's id are valid transaction ids."""
        CommandRequest(transaction_id=f"{self.tag}-0", rider=self.link.rider_id)

    def forget_keys(self) -> None:
        """The command keys' names (their declarations went with the link)."""
        self._keys.clear()

    def command(
        self, command: Command, request: CommandRequest | None, check: bool, timeout: float | None
    ) -> Reply:
        """Send one command (`Rider.command`)."""
        # A command may move a ride: a default machine is looked up with more certainty.
        self.machines.pick(motion=True)
        retries = self.link.retries
        # Until when this call waits, counted from the request's timecode (a request sent
        # again later, same transaction, waits anew): a motion command that reaches the
        # machine after that (a frozen daemon resuming) is refused there, not acted unseen.
        wait = (timeout if timeout is not None else self.link.timeout) * (retries + 1)
        if request is None:
            payload = self._own_request(min(wait, VALID_FOR_MAX_S))
        else:
            if request.valid_for is None:
                now = time.time()
                sent = request.timecode if request.timecode is not None else now
                valid = max(now - sent, 0.0) + wait
                request = request.model_copy(update={"valid_for": min(valid, VALID_FOR_MAX_S)})
            payload = encode(request)
        key = self._key(command)
        last: RiderError | None = None
        for _ in range(retries + 1):
            try:
                reply = self.transport.get_one(key, payload, Reply, timeout)
            except MachineTimeout as exc:
                last = exc  # same transaction id again: at most once on the machine
                continue
            if check and not reply.success:
                raise CommandRefused(reply)
            return reply
        assert last is not None
        raise last

    def _key(self, command: Command) -> str:
        """`command`'s key on this Rider's machine, declared (the machine is fixed once
        picked, and so is the prefix: worked out once per command)."""
        key = self._keys.get(command)
        if key is None:
            key = f"{self.machines.base}/cmd/{command.key}"
            self.link.declare_key(key)
            self._keys[command] = key
        return key

    def _own_request(self, valid_for: float) -> bytes:
        """A plain command's request, packed straight from its fields: the same bytes as
        `encode(CommandRequest(...))` (tests/rider/test_replies.py) without building and
        validating a model per command. Every field is the Rider's own: the id is its tag and a
        counter, the rider its session id (both checked once, at `open`); a `valid_for` that is
        no number in range (a zero timeout) or a Rider not open goes through the model, as
        before."""
        in_range = type(valid_for) in (float, int) and 0 < valid_for <= VALID_FOR_MAX_S
        if not in_range or not self.link.is_open:
            return encode(CommandRequest.model_validate(self.fields(valid_for=valid_for)))
        return pack(
            {
                "transaction_id": self.new_transaction_id(),
                "timecode": time.time(),
                "rider": self.link.rider_id if self.link.supervise else None,
                "valid_for": float(valid_for),
            }
        )

    def fields(self, **extra: Any) -> dict[str, Any]:
        """A request's own fields (a fresh id, now, who watches), with `extra`."""
        return {
            "transaction_id": self.new_transaction_id(),
            "timecode": time.time(),
            "rider": self.link.rider_id if self.link.supervise else None,
            **extra,
        }
