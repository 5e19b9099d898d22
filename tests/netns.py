"""Two network namespaces joined by a veth pair: the topology of two containers on one network.

`veth_pair()` creates them with unique names per run, gives each end an address, and always
deletes what it created, even when the test fails. Where namespaces cannot be made (not root,
no `ip`, no kernel support) it raises `NetnsUnavailable` with the reason, for a test to skip.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import subprocess
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

IP_TIMEOUT_S = 10.0
SUBNET = "10.213.7"
"""Private addresses that exist only inside the two namespaces, never on the host."""

NETNS_ETC = Path("/etc/netns")
"""`ip netns exec NS` bind-mounts every file of /etc/netns/NS over the same file in /etc."""


class NetnsUnavailable(Exception):
    """Namespaces or the veth pair cannot be created here; the message says why."""


@dataclass(frozen=True)
class NsPair:
    """Namespace `a` holds `veth_a` with `addr_a`, namespace `b` holds `veth_b` with `addr_b`."""

    a: str
    b: str
    veth_a: str
    veth_b: str
    addr_a: str
    addr_b: str

    def cmd(self, ns: str, args: Sequence[str]) -> list[str]:
        """`args` run inside namespace `ns`."""
        return ["ip", "netns", "exec", ns, *args]

    def link(self, ns: str, up: bool) -> None:
        """Bring that namespace's end of the veth up or down (a pulled cable)."""
        dev = self.veth_a if ns == self.a else self.veth_b
        _ip("netns", "exec", ns, "ip", "link", "set", dev, "up" if up else "down")


def _ip(*args: str) -> None:
    try:
        done = subprocess.run(
            ["ip", *args], capture_output=True, text=True, timeout=IP_TIMEOUT_S, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NetnsUnavailable(f"`ip {' '.join(args)}` failed: {exc}") from exc
    if done.returncode != 0:
        raise NetnsUnavailable(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")


def unavailable_reason() -> str | None:
    """Why namespaces certainly cannot be made here (cheap checks), or None to try."""
    if os.geteuid() != 0:
        return f"network namespaces need root (running as uid {os.geteuid()})"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    return None


def _kill_inside(ns: str) -> None:
    """Processes a test left in its own namespace (only the test put anything there)."""
    with contextlib.suppress(OSError, subprocess.TimeoutExpired):
        out = subprocess.run(
            ["ip", "netns", "pids", ns],
            capture_output=True,
            text=True,
            timeout=IP_TIMEOUT_S,
            check=False,
        ).stdout
        for pid in out.split():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)


def _delete(ns: str) -> None:
    _kill_inside(ns)
    with contextlib.suppress(NetnsUnavailable):
        _ip("netns", "delete", ns)


@contextlib.contextmanager
def veth_pair(prefix: str = "zt") -> Iterator[NsPair]:
    """Create two namespaces + a veth pair between them; delete both on exit, always."""
    reason = unavailable_reason()
    if reason is not None:
        raise NetnsUnavailable(reason)
    tag = f"{os.getpid() % 100000}{secrets.token_hex(2)}"
    pair = NsPair(
        a=f"{prefix}-{tag}-a",
        b=f"{prefix}-{tag}-b",
        veth_a=f"{prefix}{tag}a"[:15],  # interface names are at most 15 characters
        veth_b=f"{prefix}{tag}b"[:15],
        addr_a=f"{SUBNET}.1",
        addr_b=f"{SUBNET}.2",
    )
    created: list[str] = []
    try:
        for ns in (pair.a, pair.b):
            _ip("netns", "add", ns)
            created.append(ns)
        # Created straight inside the namespaces, so nothing is ever left in the host's.
        veth = ["link", "add", pair.veth_a, "netns", pair.a, "type", "veth"]
        _ip(*veth, "peer", "name", pair.veth_b, "netns", pair.b)
        ends = ((pair.a, pair.veth_a, pair.addr_a), (pair.b, pair.veth_b, pair.addr_b))
        for ns, dev, addr in ends:
            _ip("netns", "exec", ns, "ip", "link", "set", "lo", "up")
            _ip("netns", "exec", ns, "ip", "addr", "add", f"{addr}/24", "dev", dev)
            _ip("netns", "exec", ns, "ip", "link", "set", dev, "up")
        yield pair
    finally:
        # Deleting a namespace destroys the veth end inside it, and with it the peer.
        for ns in reversed(created):
            _delete(ns)


@contextlib.contextmanager
def hosts_file(ns: str, names: Mapping[str, str]) -> Iterator[Path]:
    """Make `names` (host name → address) resolve inside namespace `ns`, as a container's
    /etc/hosts does; the file and its directory are removed on exit, always."""
    directory = NETNS_ETC / ns
    path = directory / "hosts"
    try:
        directory.mkdir(parents=True, exist_ok=True)  # ns names are unique per test run
        lines = ["127.0.0.1 localhost", *(f"{addr} {name}" for name, addr in names.items())]
        path.write_text("\n".join(lines) + "\n")
        yield path
    finally:
        path.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            directory.rmdir()
