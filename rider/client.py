"""The Rider client: `Rider` (blocking) and `AsyncRider`, the errors they raise, and what they
return. Import from here; the client is split by job, the httpx way:

- rider/errors.py: `RiderError` and its kinds (the CLI's exit codes map them);
- rider/link.py: the Zenoh config and session (bounded handshake, liveliness token, deadman
  heartbeat) and why nothing answers (`no_link_hint`);
- rider/transport.py, rider/replies.py, rider/pinning.py: queries and their replies, decoded
  and vetted (one session answers for one machine id: `DuplicateMachine`);
- rider/machines.py (with rider/discovery.py): which machine, and the machines alive;
- rider/commands.py, rider/reads.py: commands (a fresh transaction id, retried as itself) and
  reads; rider/subscriptions.py: live publications; rider/events.py: the event history;
  rider/completions.py: how a motion ended, and waits;
- rider/blocking.py: `Rider`, the thin façade over them; rider/aio.py: `AsyncRider`.

It speaks only the wire models in `schema/` over Zenoh. Every command carries a fresh
transaction id; on a timeout the same id is retried, so a retry can never act twice.
"""

from __future__ import annotations

from .aio import AsyncRider
from .blocking import Rider
from .completions import DONE_RECHECK_S
from .discovery import DISCOVERY_MIN_S, Listing
from .errors import (
    AmbiguousMachine,
    BadCredentials,
    BadReply,
    BadRuntime,
    BusError,
    CommandRefused,
    DuplicateMachine,
    LinkLost,
    MachineTimeout,
    NoMachine,
    RiderError,
    UnknownTransaction,
    UnsureMachine,
)
from .link import (
    DEFAULT_CONNECT,
    DEFAULT_TIMEOUT_S,
    HINT_PROBE_S,
    OPEN_TIMEOUT_MIN_S,
    Heartbeat,
    bound_open_timeout,
    env_connect,
    open_session,
    rider_login,
    zenoh_config,
)
from .link import direct as _direct  # tests/service/bus/test_bus_callbacks.py compares it
from .machines import MachineInfo
from .pinning import KEY_CACHE, Holders
from .replies import Update
from .subscriptions import FOREIGN_LOG_EVERY_S, Subscription, Throttle
from .transport import EMPTY_RETRY_S

__all__ = [
    "DEFAULT_CONNECT",
    "DEFAULT_TIMEOUT_S",
    "DISCOVERY_MIN_S",
    "DONE_RECHECK_S",
    "EMPTY_RETRY_S",
    "FOREIGN_LOG_EVERY_S",
    "HINT_PROBE_S",
    "KEY_CACHE",
    "OPEN_TIMEOUT_MIN_S",
    "AmbiguousMachine",
    "AsyncRider",
    "BadCredentials",
    "BadReply",
    "BadRuntime",
    "BusError",
    "CommandRefused",
    "DuplicateMachine",
    "Heartbeat",
    "Holders",
    "LinkLost",
    "Listing",
    "MachineInfo",
    "MachineTimeout",
    "NoMachine",
    "Rider",
    "RiderError",
    "Subscription",
    "Throttle",
    "UnknownTransaction",
    "UnsureMachine",
    "Update",
    "_direct",
    "bound_open_timeout",
    "env_connect",
    "open_session",
    "rider_login",
    "zenoh_config",
]
