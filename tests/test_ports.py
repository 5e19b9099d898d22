"""The tests' own ports: never one a listener holds, another test process was given, or the
kernel may hand to an outgoing connection (run 51: a daemon's `Address already in use`)."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import pytest

from tests import procs


@pytest.fixture
def claims(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr(procs, "PORT_CLAIMS", tmp_path / "ports")
    return tmp_path / "ports"


def test_ports_are_below_the_ephemeral_range_and_each_is_given_once(claims: Path) -> None:
    low, _ = (int(p) for p in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    ports = [procs.free_port() for _ in range(200)]
    assert len(set(ports)) == 200
    assert all(procs.PORTS[0] <= p < procs.PORTS[1] < low for p in ports)
    claimed = {int(f.name) for f in claims.iterdir()}
    assert claimed >= set(ports)  # and any it found another test's daemon listening on (run 52)


def test_a_port_held_by_a_listener_or_claimed_by_another_process_is_not_given(
    claims: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with socket.socket() as held:
        busy = procs.free_port()  # in the tests' range: no outgoing connection takes its neighbours
        held.bind(("127.0.0.1", busy))
        (claims / str(busy + 1)).touch()  # another process's, fresh
        monkeypatch.setattr(procs, "PORTS", (busy, busy + 3))
        assert procs.free_port() == busy + 2
        with pytest.raises(RuntimeError, match="no free port"):
            procs.free_port()


def test_a_stale_claim_is_taken_over(claims: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    port = procs.free_port()
    stale = claims / str(port)
    old = time.time() - procs.PORT_CLAIM_S - 1
    os.utime(stale, (old, old))
    monkeypatch.setattr(procs, "PORTS", (port, port + 1))
    assert procs.free_port() == port
    assert stale.stat().st_mtime > old + 1  # claimed afresh
