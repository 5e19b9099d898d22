"""systemd's notify protocol (sd_notify(3)) for `machine supervise`, without a dependency.

One datagram per message to `$NOTIFY_SOCKET` (a path, or a name in the abstract namespace
when it starts with `@`): `READY=1` once the first daemon serves, `WATCHDOG=1` at half of
`$WATCHDOG_USEC` while the supervisor is alive. Without `NOTIFY_SOCKET` (not under systemd, or
a unit that is not `Type=notify`) nothing is sent and no socket is opened. The variables are
taken out of the environment as they are read, so the daemon child does not inherit them (as
sd_notify's `unset_environment` does): systemd hears from the supervisor alone.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import MutableMapping

log = logging.getLogger("machine.supervisor")

NOTIFY_SOCKET = "NOTIFY_SOCKET"
WATCHDOG_USEC = "WATCHDOG_USEC"
WATCHDOG_PID = "WATCHDOG_PID"


def socket_address(value: str) -> str:
    """`$NOTIFY_SOCKET` as `sendto` takes it: `@name` is `name` in the abstract namespace."""
    return "\0" + value[1:] if value.startswith("@") else value


class Notifier:
    """Tells systemd the supervisor is ready and alive; does nothing where nobody listens."""

    def __init__(self, address: str | None, watchdog_s: float | None) -> None:
        """`address`: where to send (None: nowhere); `watchdog_s`: the unit's `WatchdogSec`
        (None: no watchdog pings)."""
        self.address = address
        self.interval_s = watchdog_s / 2 if watchdog_s else None
        """How often `watchdog` pings: half the unit's limit, as sd_watchdog_enabled(3) advises."""
        self._sock: socket.socket | None = None
        self._ready = False
        self._last_ping: float | None = None
        self._failing = False
        if address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)  # a full socket drops a ping, never holds the guard

    @classmethod
    def from_env(
        cls, env: MutableMapping[str, str] | None = None, pid: int | None = None
    ) -> Notifier:
        """From systemd's variables, taken out of `env` (the process's environment); a
        watchdog meant for another process (`WATCHDOG_PID`) is not ours to feed."""
        env = os.environ if env is None else env
        value = env.pop(NOTIFY_SOCKET, "")
        usec = env.pop(WATCHDOG_USEC, "")
        owner = env.pop(WATCHDOG_PID, "")
        if not value:
            return cls(None, None)
        watchdog_s = int(usec) / 1e6 if usec.isdigit() and int(usec) > 0 else None
        if owner and owner != str(os.getpid() if pid is None else pid):
            watchdog_s = None
        return cls(socket_address(value), watchdog_s)

    def ready(self) -> None:
        """`READY=1`, once: the daemon serves (later starts change nothing for systemd)."""
        if self._sock is None or self._ready:
            return
        self._ready = True
        log.info("event=systemd_notify message=READY=1")
        self._send(b"READY=1")

    def watchdog(self, now: float) -> None:
        """`WATCHDOG=1` if half the unit's limit has passed since the last one (`now`: seconds
        on a monotonic clock); from the output guard's thread, never blocking."""
        interval = self.interval_s
        if self._sock is None or interval is None:
            return
        if self._last_ping is not None and now - self._last_ping < interval:
            return
        self._last_ping = now
        self._send(b"WATCHDOG=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _send(self, message: bytes) -> None:
        assert self._sock is not None and self.address is not None
        try:
            self._sock.sendto(message, self.address)
        except OSError as exc:  # systemd gone or busy: said once, tried again next time
            if not self._failing:
                log.warning(
                    "event=systemd_notify_failed message=%s error=%r", message.decode(), str(exc)
                )
            self._failing = True
            return
        if self._failing:
            log.info("event=systemd_notify_restored message=%s", message.decode())
            self._failing = False
