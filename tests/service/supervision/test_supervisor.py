"""The supervisor's own parts, in process: what it tells systemd and when, and how it stops a
daemon that is frozen. No child, no session: the keeper's child is a stand-in
(test_children.py), systemd a real datagram socket (test_sdnotify.py)."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.beat import BeatWriter
from ride_machine.service.supervision.assembly import DaemonOptions
from ride_machine.service.supervision.outputguard import OutputGuard
from ride_machine.service.supervision.restarts import SupervisorOptions
from ride_machine.service.supervision.sdnotify import NOTIFY_SOCKET, WATCHDOG_USEC
from ride_machine.service.supervision.supervisor import Supervisor
from tests.service.supervision.test_children import keeper_of
from tests.service.supervision.test_outputguard import Image
from tests.service.supervision.test_sdnotify import heard, nothing_more

LIMIT_S = 0.1
T0 = 1_000_000_000_000


@pytest.fixture
def supervisor(
    systemd: tuple[socket.socket, str],
    monkeypatch: pytest.MonkeyPatch,
) -> Iterator[Supervisor]:
    """A supervisor under systemd (`WatchdogSec=2`), not run."""
    _, path = systemd
    monkeypatch.setenv(NOTIFY_SOCKET, path)
    monkeypatch.setenv(WATCHDOG_USEC, "2000000")
    sup = Supervisor(MachineConfig(), DaemonOptions(), SupervisorOptions())
    yield sup
    sup._cleanup()


def test_ready_is_said_once_a_daemon_serves(
    supervisor: Supervisor,
    systemd: tuple[socket.socket, str],
) -> None:
    sock, _ = systemd
    supervisor._on_presence(False)
    assert nothing_more(sock)
    supervisor._on_presence(True)
    assert heard(sock) == b"READY=1"


@pytest.mark.hazard("H04")
def test_the_watchdog_is_fed_only_while_the_keepers_loop_comes_round(
    supervisor: Supervisor,
    systemd: tuple[socket.socket, str],
    tmp_path: Path,
) -> None:
    sock, _ = systemd
    keeper, _, _ = keeper_of(tmp_path, [])
    supervisor._vouch(T0)
    assert nothing_more(sock)  # no keeper yet: not started
    supervisor.children = keeper
    stuck_since = keeper.turned
    supervisor._vouch(round((stuck_since + keeper.turn_limit_s + 1.0) * 1e9))
    assert nothing_more(sock)  # its loop has not come round: systemd may kill it
    supervisor._vouch(round(stuck_since * 1e9))
    assert heard(sock) == b"WATCHDOG=1"


@pytest.mark.parametrize(
    ("age_s", "signals"), [(LIMIT_S / 2, ["SIGTERM"]), (2 * LIMIT_S, ["safe", "SIGKILL"])]
)
@pytest.mark.hazard("H04")
def test_a_daemon_whose_scan_stalled_is_killed_at_once_when_the_supervisor_stops(
    supervisor: Supervisor, tmp_path: Path, age_s: float, signals: list[str]
) -> None:
    did: list[str] = []
    supervisor.children, _, _ = keeper_of(tmp_path, did)
    writer = BeatWriter(supervisor.beat_fd)
    writer.start(LIMIT_S)
    writer.rec.beat_ns = T0
    supervisor.guard = OutputGuard(
        supervisor.beat,
        Image(on=False),
        on_trip=lambda stall: None,
        on_hang=lambda stall: None,
        hang_s=1.0,
        clock_ns=lambda: T0 + round(age_s * 1e9),
    )
    try:
        supervisor._stop_child()
    finally:
        writer.close()
    assert did[: len(signals)] == signals
