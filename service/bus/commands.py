"""`cmd/<command>`: decoded and run on Zenoh's own thread, between two scan cycles.

The hot path of the bus: one dictionary lookup on the key, one decode, the command under the
loop's lock, one reply (`Request.reply`, prebuilt key expression and encoding). The callback
runs on Zenoh's thread (no hand-off to a Python thread first), so it never waits there: when
the scan thread holds the loop's lock (mid-cycle), or a command is already waiting, the
command goes to `Deferred`, a thread of its own that waits for the lock in order. Before the
first scan a command is queued for the scan thread, which hands its reply to the `Outbox`.

A command that names a Rider (its `rider` field or its attachment) waits there too, while that
Rider is asked whether it sent it (service/bus/confirm.py): a motion command it does not
confirm is refused `RIDER_UNCONFIRMED`; any other is recorded with the Rider as claimed only.
A Pause or a Stop never waits behind them (`HALTS`, on a queue of their own), and a motion
command still waiting when one arrives is refused `SUPERSEDED`: the later stop wins.
"""

from __future__ import annotations

import functools
import logging

import zenoh

from ride_machine.schema.commands import REQUEST_MODELS, Command, CommandRequest, Reply
from ride_machine.schema.events import CommandEvent
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.eventlog import EventLog
from ride_machine.service.core.commands.admission import watchable
from ride_machine.service.core.commands.identity import Identity
from ride_machine.service.core.scan.port import LoopPort
from ride_machine.service.core.scan.tasks import PendingCommand
from ride_machine.service.core.statemachine import HANDLING
from ride_machine.service.errors import (
    BadRequest,
    Busy,
    EstopActive,
    MachineError,
    RiderUnconfirmed,
    Superseded,
    UnknownCommand,
    WildcardCommand,
)

from .confirm import Confirmer, Verdict
from .deferred import Deferred
from .outbox import Outbox
from .request import Request, sender_of
from .routes import Handler, Route, Wildcard

log = logging.getLogger(__name__)

LOCK_TIMEOUT_S = 0.5
"""How long a command waits for the scan thread to finish a cycle before BUSY (a stalled loop)."""
MOVES = {command: HANDLING[command].moves for command in Command}
"""The commands that set the machine moving (and name their supervising Rider)."""
HALTS = frozenset({Command.PAUSE, Command.STOP})
"""Taken from anyone at once, never behind a command that waits: stopping does not wait for a
Rider to be asked about something else."""
UNASKED = HALTS | {command for command in Command if HANDLING[command].read_only}
"""Commands whose Rider is not asked about them (a halt, a check): recorded as claimed."""
DEFERRED_MAX = 64
"""Commands waiting for the loop's lock at most; beyond this a command is refused BUSY."""


def command_route(handler: Handler, keys: tuple[str, ...] = (), *, direct: bool = False) -> Route:
    """`cmd/**`, one queryable for every command key: a query reaches one callback, where a
    queryable per command beside a `cmd/**` one made every command wait for two
    (bench/roundtrip). Any wildcard is refused, as a Zenoh error reply."""
    return Route(
        "cmd/**",
        handler,
        Wildcard.REFUSE,
        sniff=True,
        what="a command key",
        example="cmd/home",
        noun="command",
        refusal=WildcardCommand,
        keys=keys,
        direct=direct,
    )


class Commands:
    """The `cmd/**` route of one machine."""

    def __init__(
        self,
        base: str,
        port: LoopPort,
        confirmer: Confirmer | None = None,
        events: EventLog | None = None,
        outbox: Outbox | None = None,
    ) -> None:
        """`confirmer`: asks a named Rider about its request (None: nobody is asked, every
        claim is recorded as claimed); `events`: where a refusal that never reached the loop
        is recorded; `outbox`: sends the replies of commands the scan thread runs."""
        self.base = base
        self.port = port
        self.confirmer = confirmer
        self.events = events
        self.outbox = outbox or Outbox()
        self._commands = {
            f"{base}/cmd/{c.key}": (c, zenoh.KeyExpr(f"{base}/cmd/{c.key}")) for c in Command
        }
        """Exact command key → (command, its prebuilt key expression: no parsing per reply)."""
        self.deferred = Deferred(DEFERRED_MAX)
        self.urgent = Deferred(DEFERRED_MAX)
        """Pauses and Stops that found the loop's lock taken: they never wait behind `deferred`."""
        self.stops = 0
        """Pauses and Stops so far: a motion command that waited while this grew is refused."""

    def routes(self) -> list[Route]:
        keys = tuple(f"cmd/{c.key}" for c in Command)
        return [command_route(self.command, keys, direct=True)]

    def command(self, request: Request) -> None:
        """A known command key runs its command; any other key is refused."""
        target = self._commands.get(request.key)
        if target is None:
            raise self._unknown(request.key)
        command, key_expr = target
        request.command = command._value_
        if request.raw() is None:
            raise BadRequest(
                'a command needs a payload with at least a transaction_id, e.g. {"transaction_id":'
                ' "t1"}',
                path="/transaction_id",
            )
        body = request.decode(REQUEST_MODELS[command])
        if MOVES[command]:
            watchable(command, body)  # a supervisor of schema 1 could not be watched
        sender = sender_of(request.query)
        claim = None if command in UNASKED or self.confirmer is None else body.rider or sender
        queue = self.deferred
        if command in HALTS:
            self.stops += 1
            queue = self.urgent
        if claim is None and not queue.pending:
            reply = self.port.execute(command, body, sender=sender, timeout=None)
            if reply is not None:
                request.reply(reply, key_expr, self.port.wire(reply))
                return

        wait = functools.partial(
            self._wait, request, command, body, sender, key_expr, claim, self.stops
        )
        if not queue.put(wait):
            raise Busy("command queue full; retry later")

    def _wait(
        self,
        request: Request,
        command: Command,
        body: CommandRequest,
        sender: str | None,
        key_expr: zenoh.KeyExpr,
        claim: str | None,
        stops: int,
    ) -> None:
        """On a deferred thread: ask the Rider it names (`claim`), refuse it if a Pause or Stop
        came after it (`stops`: their count when it arrived), wait for the lock (BUSY if the
        scan stalls past the timeout), or queue it for the scan thread before the first scan
        and after shutdown; refused as `dispatch` would (away from it)."""

        def hand_over(reply: Reply) -> None:  # on the scan thread, which never sends (outbox.py)
            self.outbox.reply(request, reply, key_expr, self.port.wire(reply))

        try:
            identity = self._confirmed(request, command, body, claim)
            if MOVES[command] and self.stops != stops:
                if request.host.state() is MachineState.FAULT_ESTOP:  # the first reason
                    raise EstopActive(
                        f"{command.value} refused: the E-stop is active; release it, then"
                        " Resume, Home or Stop"
                    )
                raise Superseded(
                    f"{command.value} refused: a Pause or Stop arrived after it while it"
                    " waited; the later stop wins, nothing moved"
                )
            port = self.port
            reply = port.execute(
                command, body, sender=sender, identity=identity, timeout=LOCK_TIMEOUT_S
            )
            if reply is not None:
                request.reply(reply, key_expr, port.wire(reply))
            elif not port.submit(PendingCommand(command, body, hand_over, sender, identity)):
                raise Busy("command queue full; retry later")
        except MachineError as exc:
            self._refused(request, command, body, sender, exc)
            request.refuse(exc)

    def _confirmed(
        self, request: Request, command: Command, body: CommandRequest, claim: str | None
    ) -> Identity | None:
        """`claim` once its Rider confirmed the request; None if nobody was asked or it did
        not confirm (then a motion command is refused: nothing binds to a claim)."""
        if claim is None or self.confirmer is None:
            return None
        answer = self.confirmer.ask(claim, request.payload)
        verdict = answer.verdict
        if verdict is Verdict.CONFIRMED:
            return answer.identity(claim)
        if MOVES[command] and verdict is not Verdict.UNNAMED:
            raise RiderUnconfirmed(
                _unconfirmed(command, claim, verdict, self.confirmer),
                path="/rider" if body.rider else "",
            )
        return None

    def _refused(
        self,
        request: Request,
        command: Command,
        body: CommandRequest,
        sender: str | None,
        exc: MachineError,
    ) -> None:
        """A refusal that never reached the loop, into the history (an unconfirmed Rider is
        on the record: who tried to move the machine in another's name)."""
        if self.events is None or not isinstance(exc, RiderUnconfirmed | Superseded | EstopActive):
            return
        # Stamped with the wall clock and the cycle it was refused in (the loop's last), as a
        # command the loop answered is: the history orders it among that cycle's events.
        self.events.emit_now(
            CommandEvent(
                command=command.value,
                transaction_id=body.transaction_id,
                rider=body.rider or sender,
                accepted=False,
                code=exc.code.value,
                message=exc.message,
                state=request.host.state(),
            ),
            self.port.cycle(),
        )

    def _unknown(self, key: str) -> UnknownCommand:
        prefix = f"{self.base}/cmd/"
        suffix = key[len(prefix) :] if key.startswith(prefix) else key
        known = ", ".join(c.key for c in Command)
        return UnknownCommand(f"unknown command {suffix!r}; known: {known}")


def _unconfirmed(command: Command, claim: str, verdict: Verdict, confirmer: Confirmer) -> str:
    asked = f"asked on rider/{claim}/confirm"
    if verdict is Verdict.DENIED:
        why = (
            f"Rider {claim} says it did not send this request ({asked}): another sender used its id"
        )
    else:
        why = (
            f"Rider {claim} did not confirm this request within {confirmer.timeout_s:g} s ({asked}:"
            " it is not on the bus, or does not answer there, e.g. an older Rider or another"
            " client)"
        )
    return (
        f"{command.value} refused: {why}; nothing moved (send no rider field, and no attachment"
        " naming a Rider, to move unsupervised)"
    )
