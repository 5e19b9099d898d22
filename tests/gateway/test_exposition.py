"""The metrics endpoint's bounds: idle connections are closed after the read timeout, and
beyond the cap a connection is closed unread, so many of them cannot use up the gateway's file
descriptors (and its OPC UA server with them) while /metrics still answers."""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
import urllib.request
from collections.abc import Iterator

import pytest
from prometheus_client import CollectorRegistry, Gauge

from ride_machine.rider.gateway.exposition import serve

IDLE = 100
CAP = 16
READ_TIMEOUT_S = 2.0


@pytest.fixture
def endpoint() -> Iterator[int]:
    """A metrics endpoint on loopback with a small cap and a short read timeout: its port."""
    registry = CollectorRegistry()
    Gauge("exposition_probe", "a series to find", registry=registry).set(1)
    server, thread = serve(
        "127.0.0.1", 0, registry, read_timeout_s=READ_TIMEOUT_S, max_connections=CAP
    )
    yield int(server.server_address[1])
    server.shutdown()
    server.server_close()
    thread.join(timeout=2.0)


def _closed_by_server(socks: list[socket.socket], closed: set[socket.socket], until: float) -> None:
    """Add to `closed` each socket the server closed (EOF or reset) before `until`."""
    while len(closed) < len(socks) and (left := until - time.monotonic()) > 0:
        ready, _, _ = select.select([s for s in socks if s not in closed], [], [], left)
        for s in ready:
            try:
                if s.recv(1) == b"":
                    closed.add(s)
            except OSError:
                closed.add(s)


def _scrape(port: int, until: float) -> bytes:
    """GET /metrics, retried while the endpoint is full, until it answers or `until` passes."""
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=1.0) as r:
                return bytes(r.read())
        except OSError:
            if time.monotonic() > until:
                raise
            time.sleep(0.05)


def test_idle_connections_are_capped_and_timed_out_and_metrics_still_answers(
    endpoint: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="ride_machine.rider.gateway.exposition")
    threads_before = threading.active_count()
    start = time.monotonic()
    idle = [socket.create_connection(("127.0.0.1", endpoint)) for _ in range(IDLE)]
    try:
        closed: set[socket.socket] = set()
        # Past the cap a connection is closed unread, at once (not after the read timeout).
        _closed_by_server(idle, closed, time.monotonic() + READ_TIMEOUT_S / 2)
        assert len(closed) >= IDLE - CAP, f"only {len(closed)} of {IDLE} idle sockets closed"
        assert threading.active_count() <= threads_before + CAP
        body = _scrape(endpoint, start + READ_TIMEOUT_S + 3.0)
        assert b"exposition_probe 1.0" in body
        assert time.monotonic() - start < READ_TIMEOUT_S + 3.0
        # The ones held are closed by the read timeout.
        _closed_by_server(idle, closed, time.monotonic() + READ_TIMEOUT_S + 2.0)
        assert len(closed) == IDLE
    finally:
        for s in idle:
            s.close()
    refused = [r for r in caplog.records if "event=metrics_connections_refused" in r.getMessage()]
    assert len(refused) == 1, [r.getMessage() for r in caplog.records]
