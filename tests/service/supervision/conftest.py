"""The supervision tests' systemd: a real datagram socket where `NOTIFY_SOCKET` points."""

from __future__ import annotations

import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

WAIT_S = 5.0


@pytest.fixture
def systemd() -> Iterator[tuple[socket.socket, str]]:
    """systemd's end: a datagram socket bound to a path (in a short directory of /tmp: a
    socket's path has at most 107 bytes, which pytest's tmp_path can pass) and its address."""
    with tempfile.TemporaryDirectory(prefix="sdn-", dir="/tmp") as where:
        path = str(Path(where) / "notify")
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(path)
        sock.settimeout(WAIT_S)
        yield sock, path
        sock.close()
