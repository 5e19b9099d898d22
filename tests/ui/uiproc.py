"""`rider ui` as a child process for tests, and a small reader for its event stream."""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import signal
import subprocess
import time
from collections.abc import Generator, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tests.procs import REPO, START_TIMEOUT_S, Daemon, free_port, rider_cmd, stop_process

FAST_CONFIG = Path(__file__).resolve().parent / "fast.toml"
"""Quicker sim physics, so a whole ride fits in a test."""


@dataclass
class UiServer:
    """A `rider ui` child process serving on 127.0.0.1:`port`."""

    proc: subprocess.Popen[str]
    port: int
    log_path: Path

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""

    def stop(self, sig: int = signal.SIGTERM) -> int:
        return stop_process(self.proc, sig)


def start_ui(
    tmp: Path,
    daemon: Daemon,
    *,
    port: int | None = None,
    monitor: bool = False,
    extra: Sequence[str] = (),
) -> UiServer:
    """Start `rider ui` against `daemon` (`extra`: more options after `ui`) and wait until its
    page shows the machine live."""
    port = port or free_port()
    log_path = tmp / f"ui-{port}.log"
    args = [
        "--connect",
        daemon.endpoint,
        "--zenoh-config",
        str(daemon.zenoh_config),
        "--machine",
        daemon.machine_id,
        "ui",
        "--port",
        str(port),
    ]
    if monitor:
        args.append("--monitor")
    args += extra
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with log_path.open("a") as log:
        proc = subprocess.Popen(
            rider_cmd(*args), stdout=log, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=env
        )
    server = UiServer(proc, port, log_path)
    try:
        wait_live(server)
    except BaseException:
        server.stop(signal.SIGKILL)
        raise
    return server


@contextlib.contextmanager
def running_ui(tmp: Path, daemon: Daemon, **kwargs: Any) -> Iterator[UiServer]:
    server = start_ui(tmp, daemon, **kwargs)
    try:
        yield server
    finally:
        server.stop()


def wait_live(server: UiServer, timeout: float = START_TIMEOUT_S) -> None:
    """Block until the UI server answers and reports the machine link up."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            for kind, data in events(server.port, timeout=timeout):
                link = data.get("link") if kind == "snapshot" else data
                if kind in ("snapshot", "link") and link["up"]:
                    return
                if time.monotonic() > deadline:
                    break
        except ConnectionRefusedError:
            pass
        try:
            server.proc.wait(0.1)  # a bounded wait that also notices a dead server
        except subprocess.TimeoutExpired:
            continue
        raise RuntimeError(f"rider ui exited with {server.proc.returncode}:\n{server.log()}")
    raise TimeoutError(f"rider ui not live in time:\n{server.log()}")


def events(port: int, timeout: float = 10.0) -> Generator[tuple[str, Any], None, None]:
    """(event type, data) from `/api/events`, until the stream ends or `timeout` is idle."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        conn.request("GET", "/api/events")
        resp = conn.getresponse()
        kind = "message"
        while line := resp.readline():
            text = line.decode().rstrip("\r\n")
            if text.startswith("event: "):
                kind = text[len("event: ") :]
            elif text.startswith("data: "):
                yield kind, json.loads(text[len("data: ") :])
    finally:
        conn.close()


def request(
    port: int,
    method: str,
    path: str,
    body: Any = None,
    headers: dict[str, str] | None = None,
) -> tuple[int, Any]:
    """One HTTP request; the JSON body of the answer (or its text)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=15.0)
    try:
        payload = None if body is None else (body if isinstance(body, bytes) else json.dumps(body))
        hdrs = {"Content-Type": "application/json"} if body is not None else {}
        conn.request(method, path, body=payload, headers={**hdrs, **(headers or {})})
        resp = conn.getresponse()
        raw = resp.read()
        try:
            return resp.status, json.loads(raw)
        except ValueError:
            return resp.status, raw.decode(errors="replace")
    finally:
        conn.close()
