"""The keys a Rider speaks on (outside `machine/<id>`): its presence and its deadman heartbeat.

A supervising Rider holds `rider/<login>/<zid>/alive` (a liveliness token) and puts an empty
sample on `rider/<login>/<zid>/heartbeat` every `HEARTBEAT_INTERVAL_S`. `<login>` is the Zenoh
user name it logged in with (`anonymous` on the open profile), `<zid>` its session id; together
they are its Rider id (`<login>/<zid>`), the `rider` field of its motion commands. The ACL
profiles let each login declare and put under its own `rider/<login>/**` only, so one station
can neither hold nor feed another station's token or heartbeat (docs/security.md).

The machine judges the Rider that started a motion by that heartbeat, not by the token: the
token lives as long as the Rider's Zenoh lease (10 s by default), the heartbeat stops the moment
the Rider freezes, dies or loses its link.

A Rider also answers `rider/<login>/<zid>/confirm`: the machine asks it there whether it sent a
request before it binds a ride to it or records it as the sender (`confirm_key`, `digest`). The
ACL profiles let only login `<login>` declare that queryable, so under them a confirmation proves
the login; on the open profile anyone may, and it proves nothing (docs/security.md).

Schema 1 used `rider/<zid>/…` and a bare `<zid>` as the Rider id: a machine of schema 2 refuses
a motion command that names such a Rider (`BAD_PAYLOAD` at `/rider`, `outdated_rider`) instead
of running a ride whose deadman it cannot see.
"""

from __future__ import annotations

import hashlib
import re

HEARTBEAT_INTERVAL_S = 0.1
"""How often a supervising Rider puts its heartbeat; `rider_loss.timeout_s` is checked
against it."""

ANONYMOUS = "anonymous"
"""The login part of a Rider id when the Rider has no Zenoh login (the open profile)."""

CONFIRM_QUERY_BYTES = 16
"""The size of a confirmation query's payload: the request's `digest`."""
CONFIRMED = b"1"
"""A Rider's reply to a confirmation query: it sent the request with this digest. A Rider that
acts for a person it authenticated itself (the plant gateway, for its OPC UA user) adds a space
and that person's name: `1 jane` (`confirmation`, `operator_of`)."""
OPERATOR_MAX = 64
"""The longest operator name a confirmation carries (longer ones are cut)."""
DENIED = b"0"
"""... it did not (or has forgotten it: a Rider remembers its last `LEDGER_SIZE` requests)."""
LEDGER_SIZE = 4096

ALIVE_KEYS = "rider/*/*/alive"
HEARTBEAT_KEYS = "rider/*/*/heartbeat"

_LOGIN = re.compile(r"[A-Za-z0-9._+\-][A-Za-z0-9._@+\-]{0,63}")
"""A login that can be one key chunk (and one part of a transaction-id-like Rider id)."""


def login_ok(login: str) -> bool:
    """Whether `login` can name a Rider's keys (letters, digits and `._@+-`, at most 64)."""
    return _LOGIN.fullmatch(login) is not None


def rider_id(login: str, zid: str) -> str:
    """The Rider id of session `zid` logged in as `login`."""
    return f"{login}/{zid}"


def alive_key(rider: str) -> str:
    """The liveliness key of Rider `rider` (`<login>/<zid>`)."""
    return f"rider/{rider}/alive"


def heartbeat_key(rider: str) -> str:
    return f"rider/{rider}/heartbeat"


def confirm_key(rider: str) -> str:
    """Where Rider `rider` (`<login>/<zid>`) answers whether it sent a request."""
    return f"rider/{rider}/confirm"


def digest(payload: bytes) -> bytes:
    """What a confirmation asks about: 16 bytes of BLAKE2b over the request's payload, exactly
    as it went on the wire. Any change to the request (its id, time, command, Rider) changes
    it, so a station that copies another's Rider id into a request of its own is not
    confirmed, and a request replayed whole is refused as stale by its timecode."""
    return hashlib.blake2b(payload, digest_size=CONFIRM_QUERY_BYTES).digest()


def confirmation(operator: str | None = None) -> bytes:
    """The reply that confirms a request, naming the person the Rider acted for, if any."""
    name = _printable(operator or "")
    return CONFIRMED + b" " + name.encode() if name else CONFIRMED


def operator_of(reply: bytes) -> tuple[bool, str | None]:
    """Whether `reply` confirms, and the person it names (None: nobody named)."""
    if reply == CONFIRMED:
        return True, None
    if not reply.startswith(CONFIRMED + b" "):
        return False, None
    name = _printable(reply[len(CONFIRMED) + 1 :].decode(errors="replace"))
    return True, name or None


def _printable(name: str) -> str:
    """`name` without control characters, trimmed, at most `OPERATOR_MAX` characters."""
    return "".join(c for c in name if c.isprintable()).strip()[:OPERATOR_MAX]


def rider_of(key: str) -> str | None:
    """The Rider id in `rider/<login>/<zid>/alive|heartbeat`; None for anything else."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != "rider" or not split_ok(parts[1], parts[2]):
        return None
    return f"{parts[1]}/{parts[2]}"


def split_ok(login: str, zid: str) -> bool:
    """A login and a session id (hex) that make a Rider id."""
    return login_ok(login) and zid.isalnum() and len(zid) <= 32


def is_rider_id(text: str) -> bool:
    """`<login>/<zid>`, as `rider_id` makes it."""
    login, slash, zid = text.partition("/")
    return bool(slash) and split_ok(login, zid)


def login_of(rider: str) -> str:
    """The login part of a Rider id (the whole text for a schema-1 id, which has none)."""
    return rider.partition("/")[0] if "/" in rider else ""
