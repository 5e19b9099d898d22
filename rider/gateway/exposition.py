"""The metrics endpoint: prometheus_client's exposition, answering `HEAD` too (its own server
answers a HEAD `405 Method Not Allowed`, so a load balancer's or uptime checker's probe failed).

A HEAD gets the status and headers a GET would, with no body.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterable
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import make_wsgi_app
from prometheus_client.exposition import ThreadingWSGIServer
from prometheus_client.registry import CollectorRegistry

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
    def log_message(self, format: str, *args: Any) -> None:
        """Scrapes are not logged."""


def serve(host: str, port: int, registry: CollectorRegistry) -> tuple[WSGIServer, threading.Thread]:
    """Serve `registry` on `host:port` from a daemon thread (like prometheus_client's
    `start_http_server`); returns the server and its thread."""
    family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0][0]

    class Server(ThreadingWSGIServer):
        address_family = family

    httpd = make_server(host, port, with_head(make_wsgi_app(registry)), Server, _Quiet)
    thread = threading.Thread(target=httpd.serve_forever, name="metrics", daemon=True)
    thread.start()
    return httpd, thread
