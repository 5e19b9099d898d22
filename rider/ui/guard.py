"""The ASGI gate in front of every route: a foreign `Host` (DNS rebinding) gets 403 whatever it
asks, a command from a foreign or `null` `Origin` gets 403 (rider/ui/hosts.py says which)."""

from __future__ import annotations

import logging

from starlette.datastructures import Headers
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from ride_machine.rider.text import printable

from .hosts import HostPolicy

log = logging.getLogger("rider.ui")

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
"""Reads: a page of another site cannot see their answers (no CORS), so only Host matters."""
TOLD_MAX = 64
"""Distinct refused names logged (once each): a flood of made-up names cannot fill the log."""


def error(status: int, code: str, message: str, path: str = "") -> JSONResponse:
    """The UI server's own error: `{"ok": false, "error": {code, message, path}}`."""
    body = {"ok": False, "error": {"code": code, "message": message, "path": path}}
    return JSONResponse(body, status_code=status)


class HostGuard:
    """Answers only requests for the names of `policy`; commands only from its origins."""

    def __init__(self, app: ASGIApp, policy: HostPolicy) -> None:
        self.app = app
        self.policy = policy
        self._told: set[str] = set()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        host = headers.get("host")
        origin = headers.get("origin")
        default_port = 443 if scope.get("scheme") == "https" else 80
        if not self.policy.host_ok(host, default_port):
            shown = printable(host or "")[:120]
            self._tell("foreign_host", shown)
            refusal = error(
                403,
                "FOREIGN_HOST",
                f"this UI is not served as {shown!r} (it answers to {self.policy}); behind a"
                " reverse proxy, name it with rider ui --allowed-host NAME",
                "Host",
            )
        elif scope["method"] not in SAFE_METHODS and not self.policy.origin_ok(origin):
            shown = printable(origin or "")[:120]
            self._tell("foreign_origin", shown)
            refusal = error(
                403, "FOREIGN_ORIGIN", f"commands from {shown} are not accepted", "Origin"
            )
        else:
            await self.app(scope, receive, send)
            return
        await refusal(scope, receive, send)

    def _tell(self, event: str, what: str) -> None:
        key = f"{event} {what}"
        if key not in self._told and len(self._told) < TOLD_MAX:
            self._told.add(key)
            log.warning("event=ui_%s value=%r", event, what)
