"""How a motion ended: its completion notice (asked for, or waited for while the machine's
statuses and silences are told), and waiting for the machine to reach a state."""

from __future__ import annotations

import contextlib
import queue
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import zenoh

from ride_machine.schema.commands import Reply
from ride_machine.schema.completion import Completion
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MachineState, Status

from .errors import BadReply, CommandRefused, LinkLost, MachineTimeout, UnknownTransaction
from .machines import Machines
from .reads import Reads
from .replies import Update, decode_update
from .subscriptions import Subscriptions
from .transport import Transport
from .waiting import Silence

DONE_RECHECK_S = 1.0
"""`wait_done` asks for the notice this often besides listening for it."""


def transaction_of(transaction: str | Reply) -> str:
    """The id of a motion given by its id or by its command's reply."""
    tid = transaction.transaction_id if isinstance(transaction, Reply) else transaction
    if not tid:
        raise UnknownTransaction("a reply without a transaction id has no notice")
    return tid


@dataclass
class Completions:
    """Completion notices of this Rider's machine, and waits on its state."""

    machines: Machines
    transport: Transport
    subscriptions: Subscriptions
    reads: Reads

    def done(self, transaction: str | Reply, timeout: float | None = None) -> Completion | None:
        """How the motion `transaction` ended; None while it is under way (`Rider.done`)."""
        tid = transaction_of(transaction)
        try:
            key = f"{self.machines.base}/done/{tid}"
            return self.transport.get_one(key, None, Completion, timeout)
        except CommandRefused as exc:
            if exc.error.code is ErrorCode.IN_PROGRESS:
                return None
            if exc.error.code is ErrorCode.UNKNOWN_TRANSACTION:
                raise UnknownTransaction(str(exc)) from exc
            raise

    def recent(self) -> list[Completion]:
        """Every completion notice the machine remembers (`done/**`), oldest first."""
        key = f"{self.machines.base}/done/**"
        notices = self.transport.get_all(key, Completion, required=False)
        return sorted(notices, key=lambda n: n.time)

    def wait_done(
        self,
        transaction: str | Reply,
        timeout: float,
        on_status: Callable[[Status], None] | None,
        on_silence: Callable[[float], None] | None,
        quiet_s: float,
        link_limit: float | None,
    ) -> Completion:
        """Block until the completion notice of `transaction` and return it (`Rider.wait_done`
        says how)."""
        tid = transaction_of(transaction)
        q: queue.Queue[Update] = queue.Queue()
        keys = [f"done/{tid}"] + (["status"] if on_status is not None else [])
        deadline = time.monotonic() + timeout

        def on_sample(sample: zenoh.Sample) -> None:
            with contextlib.suppress(BadReply):
                update = decode_update(sample)
                if update is not None:
                    q.put(update)

        limit = link_limit if on_status is not None else None
        silence = Silence(quiet_s, on_silence, limit, time.monotonic())
        with self.subscriptions.declare(keys, on_sample):
            recheck = 0.0
            while True:
                now = time.monotonic()
                if (lost := silence.check(now)) is not None:
                    raise LinkLost(
                        f"no word from machine {self.machines.pick()} for {lost:.0f} s"
                        f" (--link-limit {link_limit:g}); {tid} not known to have ended"
                    )
                if now >= recheck:
                    recheck = now + DONE_RECHECK_S
                    # Asked for no longer than until the next recheck: a frozen machine must
                    # not hold the silence's word back by a whole reply timeout.
                    within = min(DONE_RECHECK_S, self.transport.link.timeout)
                    if (notice := self._asked(tid, within)) is not None:
                        return notice
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise MachineTimeout(f"no completion notice for {tid} within {timeout:g} s")
                try:
                    update = q.get(timeout=min(remaining, max(recheck - time.monotonic(), 0)))
                except queue.Empty:
                    continue
                if isinstance(update, Completion) and update.transaction_id == tid:
                    return update
                if isinstance(update, Status) and on_status is not None:
                    silence.heard(time.monotonic())
                    on_status(update)

    def _asked(self, tid: str, within: float) -> Completion | None:
        """The notice, asked for (waiting at most `within` s); None while the motion runs or
        the machine is down for now."""
        with contextlib.suppress(MachineTimeout):  # down for now: keep waiting
            return self.done(tid, timeout=within)
        return None

    def wait_for(
        self, states: Iterable[MachineState], timeout: float = 60.0, *, after: float = 0.0
    ) -> Status:
        """Block until the machine is in one of `states` (`Rider.wait_for`)."""
        wanted = set(states)
        deadline = time.monotonic() + timeout
        quiet = min(1.5, timeout)
        for update in self.subscriptions.watch(("status",), self.reads.status, timeout=quiet):
            if isinstance(update, Status) and update.time >= after and update.state in wanted:
                return update
            if time.monotonic() > deadline:
                break
        last = self.reads.status()  # the watch went quiet: ask once before giving up
        if last.state in wanted and last.time >= after:
            return last
        raise MachineTimeout(f"machine still {last.state} after {timeout:g} s")
