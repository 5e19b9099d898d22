"""The supervisor's own parts, in process: what it tells systemd and when, and how it stops a
daemon that is frozen. No child, no session: the keeper's child is a stand-in
(test_children.py), systemd a real datagram socket (test_sdnotify.py)."""

from __future__ import annotations

import errno
import logging
import os
import socket
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import cast

import pytest

from ride_machine.service.bus.supervisor import SupervisorBus
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.beat import BeatWriter
from ride_machine.service.supervision.assembly import DaemonOptions
from ride_machine.service.supervision.outcome import EXIT_FAILED
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


def _read_only_under(monkeypatch: pytest.MonkeyPatch, root: Path) -> None:
    """Every file opened for writing under `root` fails as on a read-only mount (the tests
    run as root, whom a 0o555 mode does not stop)."""
    real_open = os.open

    def opener(
        path: str | os.PathLike[str], flags: int, mode: int = 0o777, *, dir_fd: int | None = None
    ) -> int:
        writes = flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)
        if writes and dir_fd is None and Path(path).resolve().is_relative_to(root):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, mode, dir_fd=dir_fd)

    monkeypatch.setattr(os, "open", opener)


@pytest.mark.hazard("H39")
def test_a_read_only_data_dir_does_not_keep_the_child_from_its_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    data = tmp_path / "data"
    data.mkdir()
    config = MachineConfig.model_validate({"data_dir": str(data)})
    sup = Supervisor(config, DaemonOptions(), SupervisorOptions())
    try:
        _read_only_under(monkeypatch, data.resolve())
        sup._write_child_files(config, '{mode: "client"}')
        sup.bus = cast(SupervisorBus, None)  # the keeper only keeps it
        files = sup._keeper().files  # where the child's `run --config` reads them
        assert (files / "zenoh-child.json5").read_text() == '{mode: "client"}'
        assert tomllib.loads((files / "machine.toml").read_text())["data_dir"] == str(data)
        assert (files / "machine.toml").stat().st_mode & 0o777 == 0o600
        assert not files.is_relative_to(data)  # the child itself says the data dir is read-only
    finally:
        sup._cleanup()


def test_child_files_that_cannot_be_written_refuse_the_start_with_a_reason(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    sup = Supervisor(MachineConfig(), DaemonOptions(), SupervisorOptions())
    session = object()
    closed: list[object] = []
    monkeypatch.setattr(sup, "_open_hal", MachineConfig)
    monkeypatch.setattr(sup, "_open_session", lambda: session)
    monkeypatch.setattr(sup, "_close_session", closed.append)
    _read_only_under(monkeypatch, sup._sockdir.resolve())
    with caplog.at_level(logging.ERROR, "machine.supervisor"):
        assert sup.run() == EXIT_FAILED  # a refusal, not a traceback
    assert "event=supervisor_files_failed" in caplog.text
    assert "Read-only file system" in caplog.text
    assert closed == [session]  # what was set up is undone
    assert sup.children is None  # no child started
