"""`rider ui`: the operator web page, served by Starlette + uvicorn and fed by one Rider.

Routes: `/` the page; `/static/*` its files; `/api/config` commands, accepted states, state
colours and session presets; `/api/events` server-sent events (a snapshot, then live
updates); `/api/snapshot` the same picture once as JSON; `POST /api/cmd/<key>` one command;
`POST /api/session` checks an uploaded session. In front of them all, `HostGuard` answers only
the names the UI is served on (rider/ui/hosts.py).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

try:
    import uvicorn
    from starlette.applications import Starlette
    from starlette.middleware import Middleware
    from starlette.requests import Request
    from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
    from starlette.routing import Mount, Route
    from starlette.staticfiles import StaticFiles
except ModuleNotFoundError as exc:  # pragma: no cover - depends on the install
    raise ModuleNotFoundError(
        f"`rider ui` needs the ui extra: pip install 'ride-machine[ui]' (missing {exc.name})"
    ) from exc

from ride_machine.common.event_words import describe
from ride_machine.rider.client import MachineTimeout, Rider, RiderError
from ride_machine.rider.exits import own_options
from ride_machine.rider.text import printable, shown
from ride_machine.schema.base import WireModel
from ride_machine.schema.codec import DecodeError, Format, decode_raw, validate
from ride_machine.schema.commands import Command, Reply, Session
from ride_machine.schema.events import EventQuery, QueryError

from .bridge import Bridge, NotReady
from .catalog import BY_KEY, EVENTS_SHOWN, event_tone, ui_config
from .guard import HostGuard
from .guard import error as _error
from .hosts import BadHostRule, HostPolicy, HostRule, parse_rule
from .hub import Hub
from .view import HISTORY_S, SAMPLE_PERIOD_S, LiveView, Push, Update

log = logging.getLogger("rider.ui")

STATIC = Path(__file__).resolve().parent / "static"
KEEPALIVE_S = 0.5
"""An idle event stream sends a tick this often, so the page can tell a dead link."""
STREAM_LOST_AFTER_S = 3 * KEEPALIVE_S
"""The page counts the UI server as gone after this long without a word on its stream."""
SHUTDOWN_S = 5.0
EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
NO_CACHE = {"Cache-Control": "no-cache"}


@dataclass
class UiState:
    """Everything the routes share; lives on `app.state.ui`."""

    rider: Rider
    monitor: bool
    view: LiveView = field(default_factory=LiveView)
    hub: Hub = field(default_factory=Hub)
    bridge: Bridge | None = None

    def on_update(self, update: Update) -> None:
        """Runs on the event loop: one machine update into the view, events to the browsers."""
        for event in self.view.apply(update, time.monotonic()):
            self.hub.publish(event)

    def tick(self) -> None:
        for event in self.view.tick(time.monotonic(), time.time()):
            self.hub.publish(event)


def create_app(
    rider: Rider, *, monitor: bool = False, hosts: HostPolicy | None = None
) -> Starlette:
    """The ASGI app; its lifespan starts the bridge and always closes the Rider session.
    `hosts`: the names it answers to (default: 127.0.0.1 and localhost on port 8080)."""
    ui = UiState(rider, monitor)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        loop = asyncio.get_running_loop()

        def sink(update: Update) -> None:
            loop.call_soon_threadsafe(ui.on_update, update)

        ui.bridge = Bridge(rider, sink)
        ui.bridge.start()
        ticker = asyncio.create_task(_tick_forever(ui))
        try:
            yield
        finally:
            ui.hub.close()
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker
            stopped = await asyncio.to_thread(ui.bridge.stop, SHUTDOWN_S)
            if not stopped:
                log.error("event=ui_session_close_timeout timeout_s=%s", SHUTDOWN_S)

    app = Starlette(
        routes=[
            Route("/", index),
            Route("/api/config", config),
            Route("/api/snapshot", snapshot),
            Route("/api/events", events),
            Route("/api/session", check_session, methods=["POST"]),
            Route("/api/history", history),
            Route("/api/cmd/{key:path}", command, methods=["POST"]),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        lifespan=lifespan,
        middleware=[Middleware(HostGuard, policy=hosts or HostPolicy.serving("127.0.0.1", 8080))],
    )
    app.state.ui = ui
    return app


async def _tick_forever(ui: UiState) -> None:
    while True:
        ui.tick()
        await asyncio.sleep(SAMPLE_PERIOD_S)


def _ui(request: Request) -> UiState:
    ui: UiState = request.app.state.ui
    return ui


# ------------------------------------------------------------------------------------ routes
async def index(request: Request) -> Response:
    return FileResponse(STATIC / "index.html", headers=NO_CACHE)


async def config(request: Request) -> Response:
    ui = _ui(request)
    doc = ui_config(monitor=ui.monitor, lost_after_s=STREAM_LOST_AFTER_S, history_s=HISTORY_S)
    return JSONResponse(doc, headers=NO_CACHE)


async def snapshot(request: Request) -> Response:
    return JSONResponse(_ui(request).view.snapshot(time.time()), headers=NO_CACHE)


async def events(request: Request) -> Response:
    """Server-sent events: `snapshot` first, then `status`, `io`, `diag`, `link`, `sample`,
    and a `tick` whenever the stream would otherwise be quiet for `KEEPALIVE_S`."""
    ui = _ui(request)
    queue = ui.hub.subscribe()  # before the snapshot, so no update falls between the two
    first = ui.view.snapshot(time.time())

    async def stream() -> AsyncIterator[str]:
        try:
            yield "retry: 1000\n\n"
            yield _sse("snapshot", first)
            while True:
                try:
                    event = await asyncio.wait_for(queue.get(), KEEPALIVE_S)
                except TimeoutError:
                    event = Push("tick", {"now": time.time(), "link": ui.view.link.up})
                if event is None:
                    return
                yield _sse(event.kind, event.data)
        finally:
            ui.hub.unsubscribe(queue)

    headers = {**NO_CACHE, "X-Accel-Buffering": "no"}
    return StreamingResponse(stream(), media_type="text/event-stream", headers=headers)


async def command(request: Request) -> Response:
    """One command to the machine; the machine's refusal comes back with its message."""
    ui = _ui(request)
    if ui.monitor:
        return _error(403, "MONITOR", "this UI is read-only (rider ui --monitor): no commands")
    key = request.path_params["key"]
    info = BY_KEY.get(key)
    if info is None:
        known = ", ".join(BY_KEY)
        return _error(404, "UNKNOWN_COMMAND", f"unknown command {key!r}; known: {known}")
    if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
        # Also makes a cross-site form post impossible: JSON needs a CORS preflight.
        return _error(415, "UNSUPPORTED_MEDIA_TYPE", "send the command as application/json")
    try:
        session = _session(info.command, await request.body())
    except DecodeError as exc:
        return _error(400, exc.error.code, exc.error.message, exc.error.path)
    bridge = ui.bridge
    if bridge is None:
        return _error(503, "NOT_READY", "the UI server is starting")
    try:
        reply = await asyncio.to_thread(bridge.command, info.command, session)
    except RiderError as exc:
        return _failed(exc)
    return _reply(reply, info.label)


def _failed(exc: RiderError) -> Response:
    """What the Rider raised, as the page's error: 503 while it has no session yet, 504 when
    the machine did not answer, 502 for anything else (a bad reply, a broken session)."""
    if isinstance(exc, NotReady):
        return _error(503, "NOT_READY", str(exc))
    if isinstance(exc, MachineTimeout):
        return _error(504, "NO_REPLY", str(exc))
    return _error(502, "BAD_REPLY", str(exc))


async def history(request: Request) -> Response:
    """The machine's event history for the Events panel: `?last=N&kind=K`, newest last."""
    ui = _ui(request)
    try:
        query = EventQuery.from_params(
            {k: v for k, v in request.query_params.items() if k in ("last", "kind")}
        )
    except QueryError as exc:
        return _error(400, "BAD_PAYLOAD", str(exc), f"?{exc.param}")
    query = dataclasses.replace(query, last=min(query.last or EVENTS_SHOWN, 500))
    bridge = ui.bridge
    if bridge is None:
        return _error(503, "NOT_READY", "the UI server is starting")
    try:
        found = await asyncio.to_thread(bridge.events, query)
    except RiderError as exc:
        return _failed(exc)
    rows = [
        {
            "seq": e.seq,
            "time": e.time,
            "kind": e.kind,
            "machine_id": printable(e.machine_id),
            "text": printable(describe(e.details)),  # shown as text: no bidi or control tricks
            "tone": event_tone(e.details),
        }
        for e in found
    ]
    return JSONResponse({"ok": True, "events": rows}, headers=NO_CACHE)


async def check_session(request: Request) -> Response:
    """Validate an uploaded session (`{"session": {...}}`) without sending anything."""
    try:
        session = _session(Command.START, await request.body())
    except DecodeError as exc:
        return _error(400, exc.error.code, exc.error.message, exc.error.path)
    if session is None:
        return _error(400, "BAD_PAYLOAD", 'send {"session": {...}}', "/session")
    return JSONResponse({"ok": True, "session": session.model_dump(mode="json")})


# ----------------------------------------------------------------------------------- helpers
def _sse(kind: str, data: Any) -> str:
    return f"event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def _reply(reply: Reply, label: str) -> JSONResponse:
    body = shown(reply).model_dump(mode="json")
    body["ok"] = reply.success
    body["label"] = label
    return JSONResponse(body, status_code=200 if reply.success else 409)


def _session(command: Command, body: bytes) -> Session | None:
    """The session of a Start request body (`{"session": {...}}`), None for the default."""
    if command is not Command.START or not body.strip():
        return None
    return validate(_StartBody, decode_raw(body, Format.JSON)).session


class _StartBody(WireModel):
    """The body of `POST /api/cmd/start`."""

    session: Session | None = None


# -------------------------------------------------------------------------------------- main
class _Server(uvicorn.Server):
    """uvicorn without re-raising the signal after shutdown, so `main` returns its code."""

    def __init__(self, config: uvicorn.Config, on_exit: Callable[[], None]) -> None:
        super().__init__(config)
        self._on_exit = on_exit
        self._signalled = False

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        sigs = (signal.SIGINT, signal.SIGTERM)
        for sig in sigs:
            signal.signal(sig, self.handle_exit)
        try:
            yield
        finally:
            # Served: one more signal must not kill the process (the default action) before
            # the Rider's session has closed.
            for sig in sigs:
                signal.signal(sig, signal.SIG_IGN)

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        """Run on the main thread inside whatever the signal interrupted: the first signal
        logs and ends the event streams; a repeat only tells uvicorn (a second Ctrl-C forces
        the exit), so a stream of signals cannot nest a log line per signal (hundreds deep,
        the process ended 1 or -15 instead of 0)."""
        first = not self._signalled
        self._signalled = True  # before anything a repeat could interrupt
        super().handle_exit(sig, frame)
        if first:
            log.info("event=signal signal=%s", signal.Signals(sig).name)
            self._on_exit()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rider ui", description="Serve the operator web page.")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (0.0.0.0 in compose)")
    p.add_argument("--port", type=int, default=8080, help="TCP port (default 8080)")
    p.add_argument(
        "--allowed-host",
        action="append",
        default=[],
        type=_host_rule,
        metavar="NAME[:PORT]",
        help="one more name the page is served as, e.g. a reverse proxy's (repeatable)",
    )
    p.add_argument("--monitor", action="store_true", help="read-only: show, never command")
    p.add_argument("--prefix", default="machine", help="key prefix (default: machine)")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    return p


def main(
    argv: Sequence[str],
    connect: list[str],
    zenoh_config: Path | None,
    machine: str | None,
    zenoh_threads: int = 1,
) -> int:
    """Serve until SIGTERM/SIGINT; the Rider session is closed before returning."""
    args = own_options(build_parser(), argv)
    if isinstance(args, int):
        return args
    try:
        sock = _listen(args.host, args.port)
    except OSError as exc:
        print(f"rider ui: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    rider = Rider(
        machine,
        connect=connect,
        zenoh_config_path=zenoh_config,
        key_prefix=args.prefix,
        supervise=not args.monitor,
        zenoh_threads=zenoh_threads,
    )
    hosts = HostPolicy.serving(args.host, args.port, args.allowed_host)
    app = create_app(rider, monitor=args.monitor, hosts=hosts)
    ui: UiState = app.state.ui
    mode = "monitor" if args.monitor else "operator"
    print(f"rider ui: http://{args.host}:{args.port}/ ({mode})", file=sys.stderr, flush=True)
    print(f"rider ui: answers to {hosts}", file=sys.stderr, flush=True)
    try:
        started = _serve(app, ui.hub, sock, args.log_level)
    finally:
        sock.close()
    if ui.bridge is not None and ui.bridge.running:
        # An open Zenoh session hangs interpreter exit: end the process, bounded.
        log.error("event=ui_exit_forced reason=session_close_hung")
        os._exit(EXIT_FAILED)
    return EXIT_OK if started else EXIT_FAILED


def _serve(app: Starlette, hub: Hub, sock: socket.socket, log_level: str) -> bool:
    """Serve `app` on `sock` until SIGTERM/SIGINT; whether the server had started."""
    loop_holder: list[asyncio.AbstractEventLoop] = []

    def on_exit() -> None:
        # Ends every event stream at once, so uvicorn's graceful shutdown is not held up.
        if loop_holder:
            loop_holder[0].call_soon_threadsafe(hub.close)

    cfg = uvicorn.Config(
        app,
        log_level=log_level,
        access_log=False,
        timeout_graceful_shutdown=2,
        lifespan="on",
    )
    server = _Server(cfg, on_exit)

    async def serve() -> None:
        loop_holder.append(asyncio.get_running_loop())
        await server.serve(sockets=[sock])

    asyncio.run(serve())
    return server.started


def _host_rule(text: str) -> HostRule:
    try:
        return parse_rule(text)
    except BadHostRule as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _listen(host: str, port: int) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    sock.listen(128)  # clients queue from now on, even before uvicorn takes the socket
    return sock
