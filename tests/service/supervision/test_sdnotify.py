"""systemd's notify protocol as a real `AF_UNIX` datagram socket hears it: READY=1 once,
WATCHDOG=1 at half of `WATCHDOG_USEC` from the output guard's thread, nothing without
`NOTIFY_SOCKET`."""

from __future__ import annotations

import os
import socket
import uuid

import pytest

from ride_machine.service.core.scan.beat import BeatReader, create_beat_fd
from ride_machine.service.supervision.outputguard import OutputGuard
from ride_machine.service.supervision.sdnotify import (
    NOTIFY_SOCKET,
    WATCHDOG_PID,
    WATCHDOG_USEC,
    Notifier,
)
from tests.service.supervision.test_outputguard import Image

WAIT_S = 5.0


def heard(sock: socket.socket) -> bytes:
    return sock.recv(4096)


def nothing_more(sock: socket.socket) -> bool:
    """Nothing waiting on the socket now (its own timeout would make a wait of it)."""
    timeout = sock.gettimeout()
    sock.setblocking(False)
    try:
        sock.recv(4096)
    except BlockingIOError:
        return True
    finally:
        sock.settimeout(timeout)
    return False


def test_ready_once_and_watchdog_at_half_its_limit_reach_the_notify_socket(
    systemd: tuple[socket.socket, str],
) -> None:
    sock, path = systemd
    env = {NOTIFY_SOCKET: path, WATCHDOG_USEC: "2000000", WATCHDOG_PID: "4242", "KEEP": "1"}
    notifier = Notifier.from_env(env, pid=4242)
    assert env == {"KEEP": "1"}  # the daemon child inherits none of systemd's variables
    try:
        notifier.ready()
        notifier.ready()
        assert heard(sock) == b"READY=1"
        notifier.watchdog(100.0)
        assert heard(sock) == b"WATCHDOG=1"
        notifier.watchdog(100.9)  # within half of the 2 s limit: not again yet
        assert nothing_more(sock)
        notifier.watchdog(101.0)
        assert heard(sock) == b"WATCHDOG=1"
        assert nothing_more(sock)  # and READY=1 was said once
    finally:
        notifier.close()


def test_a_name_with_an_at_sign_is_reached_in_the_abstract_namespace() -> None:
    name = f"ride-sdnotify-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.settimeout(WAIT_S)
        notifier = Notifier.from_env({NOTIFY_SOCKET: "@" + name})
        try:
            notifier.ready()
            assert heard(sock) == b"READY=1"
        finally:
            notifier.close()


def test_without_notify_socket_nothing_is_opened_or_sent() -> None:
    notifier = Notifier.from_env({WATCHDOG_USEC: "2000000"})
    assert notifier.address is None
    notifier.ready()
    notifier.watchdog(1.0)  # no socket to send on, and no error


def test_a_watchdog_meant_for_another_process_is_not_fed(
    systemd: tuple[socket.socket, str],
) -> None:
    sock, path = systemd
    notifier = Notifier.from_env({NOTIFY_SOCKET: path, WATCHDOG_USEC: "2000000", WATCHDOG_PID: "1"})
    try:
        assert notifier.interval_s is None
        notifier.watchdog(1.0)
        notifier.ready()
        assert heard(sock) == b"READY=1"
    finally:
        notifier.close()


@pytest.mark.hazard("H04")
def test_the_output_guards_thread_feeds_the_watchdog_as_it_looks(
    systemd: tuple[socket.socket, str],
) -> None:
    sock, path = systemd
    notifier = Notifier.from_env({NOTIFY_SOCKET: path, WATCHDOG_USEC: "2000000"})
    fd = create_beat_fd()
    reader = BeatReader(fd)
    guard = OutputGuard(
        reader,
        Image(on=False),
        on_trip=lambda stall: None,
        on_hang=lambda stall: None,
        hang_s=1.0,
        after_look=lambda now_ns: notifier.watchdog(now_ns / 1e9),
    )
    guard.start()
    try:
        assert heard(sock) == b"WATCHDOG=1"  # its first look, 50 ms on (no daemon yet)
    finally:
        guard.stop()
        notifier.close()
        reader.close()
        os.close(fd)
