"""Every error the Rider client raises: `RiderError` and its kinds (mapped to exit codes)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the wire models load only where a reply is decoded: `rider --help` needs none
    from ride_machine.schema.commands import Reply


class RiderError(Exception):
    """Base of every error the Rider client raises."""


class MachineTimeout(RiderError):
    """No reply within the timeout: the machine is gone, or the network is."""


class CommandRefused(RiderError):
    """The machine answered with an error (wrong state, bad payload, ...)."""

    def __init__(self, reply: Reply) -> None:
        from ride_machine.schema.errors import (  # loaded already: `reply` is a wire model
            Error,
            ErrorCode,
        )

        error = reply.error or Error(code=ErrorCode.INTERNAL, message="refused without reason")
        where = f" at {error.path}" if error.path else ""
        super().__init__(f"{error.code}: {error.message}{where}")
        self.reply = reply
        self.error = error


class BadCredentials(RiderError):
    """A RIDER_ZENOH_* variable is incomplete or names a file that cannot be read."""


class BadRuntime(RiderError):
    """`ZENOH_RUNTIME` in the environment is a layout Zenoh cannot read."""


class BadReply(RiderError):
    """The machine's reply could not be decoded (version mismatch, corrupt data)."""


class BusError(RiderError):
    """Zenoh refused an operation (a query, a subscription): the session is broken or closed."""


class UnknownTransaction(RiderError):
    """The machine knows no motion with this transaction id (never accepted, forgotten, or
    sent before it restarted): no notice will ever come."""


class DuplicateMachine(RiderError):
    """More than one Zenoh session answers for one machine id (two daemons share it), or one
    other than the session this Rider pinned for it: no answer is "the" answer."""

    def __init__(self, machine_id: str, sessions: Iterable[str], what: str) -> None:
        self.machine_id = machine_id
        self.sessions = tuple(sessions)
        super().__init__(
            f"machine id {machine_id} is answered by more than one session"
            f" ({', '.join(self.sessions)}): {what}; stop one of the daemons or give it another"
            " --id"
        )


class LinkLost(RiderError):
    """`wait_done` heard nothing from the machine for its `link_limit` (the link stayed down)."""


class NoMachine(RiderError):
    """No machine is alive, or the one asked for is not."""


class AmbiguousMachine(RiderError):
    """Several machines are alive and none was named."""


class UnsureMachine(AmbiguousMachine):
    """None was named, and discovery never settled: the Rider cannot tell it heard of all."""
