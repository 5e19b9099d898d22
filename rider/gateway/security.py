"""Who an OPC UA session is, and what it may do: anonymous reads and browses, an operator calls.

A session's identity is a `Caller` (asyncua's `User` with a key of its own): the gateway knows
which session called a method by it (`current_caller`) and supervises each commanding session
under its own Rider id (rider/gateway/supervision.py).
"""

from __future__ import annotations

import hmac
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding

OPERATOR = UserRole.User
"""asyncua's `User` role is the gateway's operator role (no Admin: nobody edits the space)."""

_WRITE = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
_HISTORY_UPDATE = ua.NodeId(ua.ObjectIds.HistoryUpdateRequest_Encoding_DefaultBinary)


class BadUsers(ValueError):
    """The users file cannot be read or has a line that is not `user:password`."""


@dataclass(eq=False)
class Caller(User):  # type: ignore[misc]
    """One activated OPC UA session's identity; `key` is its Rider id when it commands (hex)."""

    key: str = field(default_factory=lambda: uuid.uuid4().hex)
    last_active: float = field(default_factory=time.monotonic)
    """When a request of this session last arrived (monotonic seconds)."""

    @property
    def operator(self) -> bool:
        return self.role is OPERATOR


class Rules(PermissionRuleset):  # type: ignore[misc]
    """Every session: the read side and Call (which method a session may call is the Call
    service's to say, per method: rider/gateway/calls.py). Nobody: Write, HistoryUpdate and
    the node management services (the space is the gateway's)."""

    def __init__(self) -> None:
        allowed = {ua.NodeId(t) for t in USER_TYPES} - {_WRITE, _HISTORY_UPDATE}
        self._allowed = {UserRole.Anonymous: allowed, OPERATOR: allowed}

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        if isinstance(user, Caller):
            user.last_active = time.monotonic()  # the session's own watch, for supervision
        return action_type_id in self._allowed.get(user.role, set())


def read_users(path: Path) -> dict[str, str]:
    """`user:password` lines (the operators); blank lines and `#` comments are skipped."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadUsers(f"{path}: cannot read it ({exc})") from exc
    users: dict[str, str] = {}
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise BadUsers(f"{path}:{n}: expected user:password")
        users[user] = password
    return users


def read_certificates(directory: Path) -> dict[bytes, str]:
    """Operator certificates (DER or PEM files in `directory`): DER bytes → subject name."""
    found: dict[bytes, str] = {}
    for path in sorted(directory.iterdir()):
        data = path.read_bytes()
        try:
            cert = (
                x509.load_pem_x509_certificate(data)
                if b"-----BEGIN" in data
                else x509.load_der_x509_certificate(data)
            )
        except ValueError:
            continue  # a key or a note beside the certificates
        found[cert.public_bytes(Encoding.DER)] = cert.subject.rfc4514_string()
    return found


class Users:
    """asyncua's user manager: a known user's password or a listed certificate gives the
    operator role, no credentials are anonymous, a wrong password or unknown user is refused."""

    def __init__(self, users: dict[str, str], certificates: dict[bytes, str]) -> None:
        self._users = users
        self._certificates = certificates

    def lists(self, certificate: bytes) -> bool:
        """Whether `certificate` (DER) is one of `--operator-certs`."""
        return certificate in self._certificates

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> Caller | None:
        if username is not None:
            expected = self._users.get(username)
            given = (password or "").encode()
            if expected is None or not hmac.compare_digest(expected.encode(), given):
                return None
            return Caller(role=OPERATOR, name=username)
        # asyncua hands over the user token's certificate, or else the client application's
        # on a secure channel: either, when listed, is an operator; anything else is anonymous.
        if isinstance(certificate, bytes) and certificate in self._certificates:
            return Caller(role=OPERATOR, name=self._certificates[certificate])
        return Caller(role=UserRole.Anonymous)
