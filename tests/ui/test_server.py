"""`rider ui` as a real process against a real daemon: HTTP routes, robustness, shutdown."""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import time
from pathlib import Path

import pytest

from ride_machine.schema.commands import ALLOWED_STATES, Command
from tests.probes import signal_storm
from tests.procs import REPO, STOP_TIMEOUT_S, Daemon, free_port, rider_cmd
from tests.ui.uiproc import UiServer, events, request

pytestmark = pytest.mark.integration


def test_the_page_and_its_files_are_served(ui: UiServer) -> None:
    status, html = request(ui.port, "GET", "/")
    assert status == 200
    assert '<script src="/static/app.js">' in html
    for path in ("/static/app.js", "/static/style.css"):
        status, _ = request(ui.port, "GET", path)
        assert status == 200, path
    status, _ = request(ui.port, "GET", "/static/../app.py")
    assert status == 404


def test_config_serves_the_machine_accepted_states_from_the_schema(ui: UiServer) -> None:
    status, cfg = request(ui.port, "GET", "/api/config")
    assert status == 200
    assert cfg["monitor"] is False
    by_name = {c["name"]: c for c in cfg["commands"]}
    assert set(by_name) == {c.value for c in Command}
    for command, states in ALLOWED_STATES.items():
        assert set(by_name[command.value]["states"]) == {s.value for s in states}
    assert by_name["Start"]["confirm"] and by_name["Home"]["confirm"]
    assert by_name["CheckHome"]["with_estop"] and not by_name["Home"]["with_estop"]
    assert cfg["tones"]["FAULT_ESTOP"] == "fault"
    assert cfg["sessions"][0]["id"] == "default"


def test_event_stream_starts_with_a_snapshot_then_goes_live(ui: UiServer) -> None:
    seen: dict[str, object] = {}
    for kind, data in events(ui.port):
        seen.setdefault(kind, data)
        if {"snapshot", "sample", "diag"} <= seen.keys():
            break
    first = next(iter(seen))
    assert first == "snapshot"
    snap = seen["snapshot"]
    assert isinstance(snap, dict)
    assert snap["link"] == {"up": True, "reason": "", "machine": "m1"}
    assert snap["status"]["state"] == "WARNING_NEEDS_CALIBRATION"
    assert {p["name"] for p in snap["io"]} >= {"estop", "rotateRelay", "tiltPosition"}


@pytest.mark.hazard("H50")
def test_commands_answer_with_the_machine_reply_or_a_clear_error(ui: UiServer) -> None:
    status, body = request(ui.port, "POST", "/api/cmd/start", {})
    assert status == 409
    assert body["error"]["code"] == "NOT_CALIBRATED"
    assert "not calibrated" in body["error"]["message"]

    status, body = request(ui.port, "POST", "/api/cmd/check/home", {})
    assert status == 200
    assert body["ok"] is True
    assert body["result"]["ok"] is False

    status, body = request(ui.port, "POST", "/api/cmd/launch", {})
    assert (status, body["error"]["code"]) == (404, "UNKNOWN_COMMAND")

    status, body = request(
        ui.port, "POST", "/api/cmd/home", b"{}", headers={"Content-Type": "text/plain"}
    )
    assert (status, body["error"]["code"]) == (415, "UNSUPPORTED_MEDIA_TYPE")

    status, body = request(
        ui.port, "POST", "/api/cmd/home", {}, headers={"Origin": "http://evil.example"}
    )
    assert (status, body["error"]["code"]) == (403, "FOREIGN_ORIGIN")

    bad = {"session": {"steps": [{"kind": "tilt", "degrees": "steep"}]}}
    status, body = request(ui.port, "POST", "/api/cmd/start", bad)
    assert status == 400
    assert body["error"]["path"] == "/session/steps/0/degrees"

    status, body = request(ui.port, "POST", "/api/cmd/start", b"[1, 2", headers={})
    assert status == 400
    assert body["error"]["code"] == "BAD_PAYLOAD"

    same_origin = {"Origin": f"http://127.0.0.1:{ui.port}"}
    status, body = request(ui.port, "POST", "/api/cmd/check/calibration", {}, same_origin)
    assert status == 200


def test_session_check_validates_without_sending(ui: UiServer) -> None:
    ok = {"session": {"name": "s", "steps": [{"kind": "rotate", "revolutions": 2}]}}
    status, body = request(ui.port, "POST", "/api/session", ok)
    assert status == 200
    assert body["session"]["steps"][0]["direction"] == "cw"
    status, body = request(ui.port, "POST", "/api/session", {"session": {"steps": []}})
    assert (status, body["error"]["path"]) == (400, "/session/steps")


def test_browsers_that_vanish_mid_stream_never_break_the_bridge(ui: UiServer) -> None:
    for _ in range(5):
        with socket.create_connection(("127.0.0.1", ui.port), timeout=5) as s:
            s.sendall(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{ui.port}\r\n\r\n".encode())
            assert b"event: snapshot" in _read_until(s, b"event: snapshot")
            # Reset, not a polite close: what a crashed tab or a pulled cable looks like.
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    samples = 0
    for kind, _ in events(ui.port):
        samples += kind == "sample"
        if samples >= 3:
            break
    status, body = request(ui.port, "POST", "/api/cmd/check/home", {})
    assert status == 200 and body["ok"]
    assert "Traceback" not in ui.log()


def test_sigterm_closes_the_rider_session_and_exits_zero(ui: UiServer) -> None:
    stream = events(ui.port)
    assert next(stream)[0] == "snapshot"  # an open event stream must not hold shutdown up
    ui.proc.send_signal(signal.SIGTERM)
    assert ui.proc.wait(STOP_TIMEOUT_S) == 0
    stream.close()
    assert "event=ui_session_closed" in ui.log()


def test_a_signal_storm_stops_the_ui_once_and_exits_zero(ui: UiServer) -> None:
    """A repeat nests no log line per signal in the one before (hundreds deep, the process
    then ended 1 or -15): only the first is told, and the session still closes."""
    assert signal_storm(ui.proc.pid) > 1
    assert ui.proc.wait(STOP_TIMEOUT_S) == 0
    assert ui.log().count("event=signal ") == 1
    assert "event=ui_session_closed" in ui.log()


def test_a_busy_port_is_a_clear_usage_error(fast_daemon: Daemon) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        proc = subprocess.run(
            rider_cmd("--connect", fast_daemon.endpoint, "ui", "--port", str(port)),
            capture_output=True,
            text=True,
            timeout=30,
            cwd=REPO,
            check=False,
        )
    assert proc.returncode == 2
    assert f"cannot listen on 127.0.0.1:{port}" in proc.stderr


def test_without_a_machine_the_page_says_so_and_commands_are_refused(tmp_path: Path) -> None:
    port = free_port()
    nobody = f"tcp/127.0.0.1:{free_port()}"
    log_path = tmp_path / "ui.log"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            rider_cmd("--connect", nobody, "ui", "--port", str(port)),
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO,
            env=env,
        )
    server = UiServer(proc, port, log_path)
    try:
        reason = _first_reason(server, "searching")
        assert "no machine is alive" in reason
        status, body = request(port, "POST", "/api/cmd/home", {})
        assert (status, body["error"]["code"]) == (503, "NOT_READY")
    finally:
        assert server.stop() == 0, server.log()


def _first_reason(server: UiServer, word: str, timeout: float = 20.0) -> str:
    """The link reason once it mentions `word` (the server may still be starting)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            for kind, data in events(server.port):
                link = data["link"] if kind == "snapshot" else data
                if kind in ("snapshot", "link") and word in link["reason"]:
                    return str(link["reason"])
                if time.monotonic() > deadline:
                    break
        except ConnectionRefusedError:
            try:
                server.proc.wait(0.1)  # bounded; also notices a server that died
            except subprocess.TimeoutExpired:
                continue
            raise RuntimeError(server.log()) from None
    raise AssertionError(f"no link reason with {word!r}:\n{server.log()}")


def _read_until(s: socket.socket, marker: bytes) -> bytes:
    data = b""
    while marker not in data:
        chunk = s.recv(4096)
        if not chunk:
            break
        data += chunk
    return data
