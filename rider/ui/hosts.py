"""Which names `rider ui` answers to, against DNS rebinding and pages of other sites.

A page on a name its author controls can make that name resolve to 127.0.0.1 (DNS rebinding):
the browser then counts the UI as that page's own origin and lets it post commands and read
replies. The `Host` header still carries the attacker's name, so only the names the UI is
served on are answered (`HostPolicy.host_ok`); a command must come without an `Origin` (not a
browser) or from one of those names (`origin_ok`), never from `null` (a sandboxed frame, a
file or a data URL).
"""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Iterable
from dataclasses import dataclass
from urllib.parse import urlsplit

DEFAULT_PORTS = {"http": 80, "https": 443}
WILDCARDS = ("", "0.0.0.0", "::")


@dataclass(frozen=True, slots=True)
class HostRule:
    """One name the UI answers to; `port` None: on any port (a reverse proxy's, a mapped one)."""

    name: str
    port: int | None = None

    def matches(self, name: str, port: int) -> bool:
        return name == self.name and (self.port is None or port == self.port)

    def __str__(self) -> str:
        shown = f"[{self.name}]" if ":" in self.name else self.name
        return shown if self.port is None else f"{shown}:{self.port}"


class BadHostRule(ValueError):
    """An `--allowed-host` that is not `NAME` or `NAME:PORT`."""


def parse_rule(text: str) -> HostRule:
    """`NAME`, `NAME:PORT`, `IP`, `[IPv6]:PORT` (what a browser's address bar would hold)."""
    if not text or "/" in text or "@" in text or text.strip() != text:
        raise BadHostRule(f"{text!r}: give a host name, optionally with :PORT (not a URL)")
    try:
        parts = urlsplit(f"//{text}")
        port = parts.port
    except ValueError as exc:
        raise BadHostRule(f"{text!r}: {exc}") from None
    if not parts.hostname:
        raise BadHostRule(f"{text!r}: no host name")
    return HostRule(parts.hostname, port)


def _authority(text: str, default_port: int) -> tuple[str, int] | None:
    """(lower-case name, port) of a `Host` value or an origin's authority; None if malformed."""
    if not text or "@" in text or "/" in text:
        return None
    try:
        parts = urlsplit(f"//{text}")
        port = parts.port
    except ValueError:
        return None
    if not parts.hostname:
        return None
    return parts.hostname, default_port if port is None else port


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


@dataclass(frozen=True, slots=True)
class HostPolicy:
    """The names the UI is served on; `any_ip`: every IP address too (a wildcard bind, where
    the addresses are the machine's own: rebinding needs a name, never an address)."""

    rules: tuple[HostRule, ...]
    any_ip: bool = False

    @classmethod
    def serving(cls, host: str, port: int, allowed: Iterable[HostRule] = ()) -> HostPolicy:
        """The policy of `rider ui --host HOST --port PORT --allowed-host ...`."""
        extra = tuple(allowed)
        if host in WILDCARDS:
            # Reached by whatever address or port mapping leads here (compose publishes
            # 127.0.0.1:8080 → 8080): any address and the machine's own names, any port.
            own = {"localhost", socket.gethostname().lower()}
            return cls((*(HostRule(n) for n in sorted(own) if n), *extra), any_ip=True)
        name = host.strip("[]").lower()
        names = [name]
        if _is_ip(name) and ipaddress.ip_address(name).is_loopback:
            names.append("localhost")  # the browser's other name for the same address
        return cls((*(HostRule(n, port) for n in names), *extra))

    def host_ok(self, header: str | None, default_port: int = 80) -> bool:
        """Whether a request's `Host` names this UI."""
        found = _authority(header or "", default_port)
        return found is not None and self._known(*found)

    def origin_ok(self, origin: str | None) -> bool:
        """Whether a command may come from `origin`: none (not a browser) or one of ours."""
        if origin is None:
            return True
        parts = urlsplit(origin)
        default = DEFAULT_PORTS.get(parts.scheme)
        if default is None or parts.path or parts.query:
            return False  # `null`, file:, data:, or not an origin at all
        found = _authority(parts.netloc, default)
        return found is not None and self._known(*found)

    def _known(self, name: str, port: int) -> bool:
        if self.any_ip and _is_ip(name):
            return True
        return any(rule.matches(name, port) for rule in self.rules)

    def __str__(self) -> str:
        names = [str(r) for r in self.rules]
        return ", ".join(names + (["any IP address"] if self.any_ip else []))
