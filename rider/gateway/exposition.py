"""The metrics endpoint: prometheus_client's exposition, answering `HEAD` too (its own server
answers a HEAD `405 Method Not Allowed`, so a load balancer's or uptime checker's probe failed).

A HEAD gets the status and headers a GET would, with no body.

Each connection has a thread of its own, so the endpoint bounds them: a connection that sends
nothing for `READ_TIMEOUT_S` is closed, and beyond `MAX_CONNECTIONS` at once a new one is closed
unread (logged once per burst). Without the bounds ~1,000 idle connections used up the process's
file descriptors and took the OPC UA server down with the metrics.
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Callable, Iterable
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import make_wsgi_app
from prometheus_client.exposition import ThreadingWSGIServer
from prometheus_client.registry import CollectorRegistry

log = logging.getLogger(__name__)

READ_TIMEOUT_S = 10.0
"""The longest a connection may stay silent (a scrape sends its request at once)."""
MAX_CONNECTIONS = 64
"""Connections served at once; more are closed unread (a scraper retries at its next interval)."""

Wsgi = Callable[[dict[str, Any], Callable[..., Any]], Iterable[bytes]]


def with_head(app: Wsgi) -> Wsgi:
    """`app`, with HEAD answered as GET without the body."""

    def wrapped(environ: dict[str, Any], start_response: Callable[..., Any]) -> Iterable[bytes]:
        if environ.get("REQUEST_METHOD") != "HEAD":
            return app(environ, start_response)
        answer: list[Any] = []

        def keep(status: str, headers: list[tuple[str, str]], *exc: Any) -> None:
            answer[:] = [status, headers]

        body = b"".join(app({**environ, "REQUEST_METHOD": "GET"}, keep))
        status, headers = answer
        headers = [(k, v) for k, v in headers if k.lower() != "content-length"]
        start_response(status, [*headers, ("Content-Length", str(len(body)))])
        return []

    return wrapped


class _Quiet(WSGIRequestHandler):
    timeout = READ_TIMEOUT_S  # StreamRequestHandler sets it on the socket

    def handle(self) -> None:
        try:
            super().handle()
        except OSError:  # silent past the timeout, or gone: the connection just closes
            self.close_connection = True

    def log_message(self, format: str, *args: Any) -> None:
        """Scrapes are not logged."""


class BoundedServer(ThreadingWSGIServer):
    """A thread per connection, at most `max_connections` of them; more are closed unread."""

    max_connections = MAX_CONNECTIONS
    request_queue_size = 128  # socketserver's 5 drops SYNs in a burst (a 1 s retry each)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._slots = threading.BoundedSemaphore(self.max_connections)
        self._refused = 0  # in the current burst; 0 when the last connection was served
        super().__init__(*args, **kwargs)

    def verify_request(self, request: Any, client_address: Any) -> bool:
        if self._slots.acquire(blocking=False):
            if self._refused:
                log.info("event=metrics_connections_served_again refused=%d", self._refused)
                self._refused = 0
            return True
        if not self._refused:
            log.warning("event=metrics_connections_refused limit=%d", self.max_connections)
        self._refused += 1
        return False

    def process_request(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request(request, client_address)
        except BaseException:  # no thread started: it will not release the slot
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


def serve(
    host: str,
    port: int,
    registry: CollectorRegistry,
    *,
    read_timeout_s: float = READ_TIMEOUT_S,
    max_connections: int = MAX_CONNECTIONS,
) -> tuple[WSGIServer, threading.Thread]:
    """Serve `registry` on `host:port` from a daemon thread (like prometheus_client's
    `start_http_server`), bounded as the module says; returns the server and its thread."""
    family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0][0]

    class Server(BoundedServer):
        address_family = family

    class Handler(_Quiet):
        timeout = read_timeout_s

    Server.max_connections = max_connections
    httpd = make_server(host, port, with_head(make_wsgi_app(registry)), Server, Handler)
    thread = threading.Thread(target=httpd.serve_forever, name="metrics", daemon=True)
    thread.start()
    return httpd, thread
