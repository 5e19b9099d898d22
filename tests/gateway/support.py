"""The plant stand for the gateway's tests: a site (router + daemons, tests/site/stand.py), a
`rider gateway` process joined to it, its credentials, and bounded waits on what clients see."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from ride_machine.service.adapters.opcua_credentials import (
    CERTIFICATE,
    OPERATOR,
    PRIVATE_KEY,
    USERS,
    init_opcua,
)
from tests.procs import REPO, Daemon, free_port, stop_process
from tests.site.stand import Lines, Site

T = TypeVar("T")
NAMESPACE = "urn:ride-machine:gateway"
SESSION_TIMEOUT_S = 2.0
"""The longest OPC UA session timeout the test gateway grants."""
FORGET_AFTER_S = 1.0
WAIT_S = 20.0
"""Bound of a wait for something a client should see (generous: a loaded CI host)."""


@dataclass(frozen=True)
class Credentials:
    """What `machine credentials init` makes for the gateway: certificate, key, operators."""

    certificate: Path
    private_key: Path
    users: Path
    password: str


def make_credentials(directory: Path) -> Credentials:
    """With the code `machine credentials init` runs, so the tests check its files too."""
    init_opcua(directory)
    line = (directory / USERS).read_text().strip()
    user, _, password = line.partition(":")
    assert user == OPERATOR
    return Credentials(
        directory / CERTIFICATE, directory / PRIVATE_KEY, directory / USERS, password
    )


@dataclass
class GatewayProc:
    """A `rider gateway` child: its OPC UA and metrics endpoints, its output lines."""

    proc: subprocess.Popen[str]
    lines: Lines
    opcua_port: int
    metrics_port: int

    @property
    def url(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.opcua_port}/"

    @property
    def metrics_url(self) -> str:
        return f"http://127.0.0.1:{self.metrics_port}/metrics"

    def scrape(self) -> str:
        with urllib.request.urlopen(self.metrics_url, timeout=5) as r:
            return str(r.read().decode())

    def stop(self) -> int:
        return stop_process(self.proc, signal.SIGTERM)


GATEWAY_START_S = 60.0
"""Bound for `rider gateway` to say it serves. Its start is ~4 s of CPU on a quiet 2-core host
(1.3 s of imports, 2.4 s in asyncua's `Server.init` filling the standard address space); a
host loaded four deep stretched it past the daemons' 20 s (run 71 under load: no output at all
in 20 s, and the package's seven tests errored at setup)."""


def start_gateway(
    rider: list[str], creds: Credentials, *more: str, env: dict[str, str] | None = None
) -> GatewayProc:
    """`rider gateway` after the Rider options `rider` (`rider --connect …`); returns once it
    serves."""
    opcua, metrics = free_port(), free_port()
    cmd = [
        *rider,
        "gateway",
        *["--opcua", f"127.0.0.1:{opcua}", "--metrics", f"127.0.0.1:{metrics}"],
        *["--users", str(creds.users), "--certificate", str(creds.certificate)],
        *["--private-key", str(creds.private_key)],
        *["--session-timeout", str(SESSION_TIMEOUT_S), "--forget-after", str(FORGET_AFTER_S)],
        *more,
    ]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=REPO,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
    )
    gateway = GatewayProc(proc, Lines(proc), opcua, metrics)
    try:
        gateway.lines.wait_for("event=gateway_ready", GATEWAY_START_S)
    except BaseException:
        stop_process(proc, signal.SIGKILL)
        raise
    return gateway


@contextlib.contextmanager
def running_gateway(
    rider: list[str], creds: Credentials, *more: str, env: dict[str, str] | None = None
) -> Iterator[GatewayProc]:
    gateway = start_gateway(rider, creds, *more, env=env)
    try:
        yield gateway
    except BaseException:
        gateway.stop()
        raise
    # SIGTERM: its sessions and the Zenoh session closed, exit 0 (an open session would hang).
    assert gateway.stop() == 0
    gateway.lines.wait_for("event=gateway_stopped")


def until(what: str, probe: Callable[[], T | None], timeout: float = WAIT_S) -> T:
    """Poll `probe` until it returns something (not None), bounded."""
    deadline = time.monotonic() + timeout
    while True:
        got = probe()
        if got is not None:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        time.sleep(0.05)


def python_client(script: str, *args: str) -> subprocess.Popen[str]:
    """A separate Python process (a client that can be frozen or killed on its own)."""
    return subprocess.Popen(
        [sys.executable, "-c", script, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )


@contextlib.contextmanager
def joined(plant: Site, machine_id: str) -> Iterator[Daemon]:
    """A machine of the test's own on the plant (one that is frozen, E-stopped or killed must
    not disturb the package's m1); stopped after, thawed first if it was frozen."""
    plant.start_daemons({machine_id: "client"})
    try:
        yield plant.daemons[machine_id]
    finally:
        if machine_id in plant.daemons:
            with contextlib.suppress(ProcessLookupError):
                plant.daemons[machine_id].proc.send_signal(signal.SIGCONT)
            plant.daemons.pop(machine_id).stop()
