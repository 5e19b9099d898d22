"""`cmd/<command>`: decoded and run on Zenoh's callback thread, between two scan cycles.

The hot path of the bus: one dictionary lookup on the key, one decode, the command under the
loop's lock, one reply (`Request.reply`, prebuilt key expression and encoding).
"""

from __future__ import annotations

from collections.abc import Callable

import zenoh

from schema.commands import REQUEST_MODELS, Command, Reply
from service.bus.request import Request, sender_of
from service.bus.routes import Handler, Route, Wildcard
from service.core.loop import PendingCommand, ScanLoop
from service.errors import BadRequest, Busy, UnknownCommand, WildcardCommand

LOCK_TIMEOUT_S = 0.5
"""How long a command waits for the scan thread to finish a cycle before BUSY (a stalled loop)."""


def command_route(handler: Handler, keys: tuple[str, ...] = ()) -> Route:
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
    )


class Commands:
    """The `cmd/**` route of one machine."""

    def __init__(self, base: str, loop: ScanLoop, clock: Callable[[], float]) -> None:
        self.base = base
        self.loop = loop
        self.clock = clock
        """The scan loop's clock (the runner's), for commands run between cycles."""
        self._commands = {
            f"{base}/cmd/{c.key}": (c, zenoh.KeyExpr(f"{base}/cmd/{c.key}")) for c in Command
        }
        """Exact command key → (command, its prebuilt key expression: no parsing per reply)."""

    def routes(self) -> list[Route]:
        return [command_route(self.command, tuple(f"cmd/{c.key}" for c in Command))]

    def command(self, request: Request) -> None:
        """A known command key runs its command; any other key is refused."""
        target = self._commands.get(request.key)
        if target is None:
            raise self._unknown(request.key)
        command, key_expr = target
        request.command = command.value
        if request.raw() is None:
            raise BadRequest(
                'a command needs a payload with at least a transaction_id, e.g. {"transaction_id":'
                ' "t1"}',
                path="/transaction_id",
            )
        body = request.decode(REQUEST_MODELS[command])
        sender = sender_of(request.query)
        reply = self.loop.execute_between_cycles(
            command, body, self.clock, sender=sender, timeout=LOCK_TIMEOUT_S
        )
        if reply is not None:
            request.reply(reply, key_expr)
            return

        # Before the first scan (no input image yet) or after shutdown: the scan thread decides.
        def respond(reply: Reply) -> None:
            request.reply(reply, key_expr)

        if not self.loop.inbox.put(PendingCommand(command, body, respond, sender)):
            raise Busy("command queue full; retry later")

    def _unknown(self, key: str) -> UnknownCommand:
        prefix = f"{self.base}/cmd/"
        suffix = key[len(prefix) :] if key.startswith(prefix) else key
        known = ", ".join(c.key for c in Command)
        return UnknownCommand(f"unknown command {suffix!r}; known: {known}")
