"""The machine's Zenoh adapter; this package alone (with the Rider's client) imports `zenoh`.

Queryables are a table of routes (`routes.py`): each query becomes one `Request` (key, format,
payload), a handler answers it with `reply` or raises a `MachineError`, and `Request.refuse`
turns that into the one refusal shape. A command runs on Zenoh's own thread, between two scan
cycles, under the loop's lock (one writer at a time; the next cycle still reads inputs and
handles E-stop before any output changes) and is answered from the same thread: no hand-off.
It never waits there: while the scan holds the lock, the command waits on a thread of its own
(`deferred.Deferred`), in arrival order. Work done on the scan thread is answered from a
thread of its own (`outbox.Outbox`): a reply takes the asker's QoS and may wait on its link,
so a caller that stops reading never stalls the scan.
The bus sees the loop only through its port (`service.core.scan.port.LoopPort`): a command between
cycles, any other work as a task for the scan thread (`service.core.scan.tasks`), the published
records as one immutable value; the loop publishes through the bus's `Publications`, its sink.
Read-only queries (status, IO, axes, diagnostics) are answered from those records without
touching state. Publishers drop rather than block under congestion.

Modules by role: `request` (one query, one reply function), `routes` (the table and the
wildcard rule), `commands`, `reads`, `writes`, `injection` (`sim/**` through `SimPort`),
`publications`, `presence` (duplicates, Riders), `callbacks` (Zenoh's threads keep their
Python state), `deferred` and `outbox` (work and replies off the caller's thread), `session`
(config, open, close), `zenoh_bus` (the daemon's bus), `supervisor` (the supervisor's),
`exposure`.
"""

from ride_machine.common.runtime import use_runtime
from ride_machine.common.zenoh_session import file_config, open_session

from .commands import LOCK_TIMEOUT_S
from .injection import SimPort
from .presence import holders_of
from .publications import Publications
from .reads import ConfigChecker
from .request import ENCODINGS, Request, reply_format
from .session import DEFAULT_LISTEN, Session, close_session, zenoh_config
from .writes import ParamService
from .zenoh_bus import ZenohBus

__all__ = [
    "DEFAULT_LISTEN",
    "ENCODINGS",
    "LOCK_TIMEOUT_S",
    "ConfigChecker",
    "ParamService",
    "Publications",
    "Request",
    "Session",
    "SimPort",
    "ZenohBus",
    "close_session",
    "file_config",
    "holders_of",
    "open_session",
    "reply_format",
    "use_runtime",
    "zenoh_config",
]
