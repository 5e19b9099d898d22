"""Safe defaults: loopback unless told otherwise, a warning when exposed without a login, and
`machine credentials init` making the login files the ACL profiles read."""

from __future__ import annotations

import os
import stat
import subprocess
import time
from pathlib import Path

import pytest

from ride_machine.common.credentials import RIDER, zenoh_settings
from ride_machine.service.adapters.credentials import DICTIONARY, identities, password_file
from tests import procs
from tests.netns import NetnsUnavailable, veth_pair
from tests.procs import REPO, START_TIMEOUT_S, free_port, machine_cmd, stop_process
from tests.reliability.support import ACL_PROFILE

pytestmark = pytest.mark.integration

WARNING = "event=listen_unauthenticated"


def wait_log(log: Path, proc: subprocess.Popen[str], needle: str) -> str:
    """The log once `needle` is in it (bounded; fails early when the process exits)."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        text = log.read_text() if log.exists() else ""
        if needle in text:
            return text
        assert proc.poll() is None, f"exited with {proc.returncode}:\n{text}"
        time.sleep(0.05)  # polling a file we do not own: no event to wait on
    raise AssertionError(f"no {needle!r} within {START_TIMEOUT_S:g} s:\n{log.read_text()}")


def run_machine(
    tmp: Path, *args: str, prefix: list[str] | None = None, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen[str], Path]:
    log = tmp / "machine.log"
    cmd = [*(prefix or []), *machine_cmd("run", "--sim", "--data-dir", str(tmp / "data"), *args)]
    with log.open("w") as fh:
        proc = subprocess.Popen(
            cmd,
            stdout=fh,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
    return proc, log


@pytest.mark.hazard("H32")
def test_without_listen_the_daemon_listens_on_loopback_only(tmp_path: Path) -> None:
    try:
        with veth_pair("sd") as net:
            # Its own namespace: port 7447 is free there whatever else runs on this host.
            proc, log = run_machine(tmp_path, prefix=net.cmd(net.a, []))
            try:
                text = wait_log(log, proc, "event=started")
                listening = subprocess.run(
                    net.cmd(net.a, ["ss", "-ltnH"]),
                    capture_output=True,
                    text=True,
                    timeout=10,
                    check=True,
                ).stdout.splitlines()
            finally:
                stop_process(proc)
    except NetnsUnavailable as exc:
        pytest.skip(f"cannot create network namespaces here: {exc}")
    ports = [line.split()[3] for line in listening if line.strip()]
    assert [p for p in ports if p.endswith(":7447")] == ["127.0.0.1:7447"], ports
    assert WARNING not in text


@pytest.mark.hazard("H32")
def test_listening_beyond_loopback_without_a_login_warns_how_to_turn_it_on(tmp_path: Path) -> None:
    proc, log = run_machine(tmp_path, "--listen", f"tcp/0.0.0.0:{free_port()}")
    try:
        text = wait_log(log, proc, "event=started")
    finally:
        stop_process(proc)
    (line,) = [x for x in text.splitlines() if WARNING in x]
    assert "0.0.0.0" in line and "zenoh/acl.json5" in line
    assert "machine credentials init" in line


@pytest.mark.hazard("H33")
def test_credentials_init_makes_files_an_acl_daemon_starts_with(tmp_path: Path) -> None:
    secrets = tmp_path / "secrets"
    done = procs.run_machine("credentials", "init", str(secrets))
    assert done.returncode == 0, done.stderr
    made = identities()  # one login per station, none shared (issue 58, point 3)
    assert "rider" not in made and {"ui", "gateway"} <= set(made)
    files = [password_file(secrets, u) for u in made] + [secrets / DICTIONARY]
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in files)
    assert stat.S_IMODE(secrets.stat().st_mode) == 0o700
    lines = dict(line.split(":", 1) for line in (secrets / DICTIONARY).read_text().splitlines())
    assert set(lines) == set(made)
    env = {
        "RIDER_ZENOH_USER": "ui",
        "RIDER_ZENOH_PASSWORD_FILE": str(password_file(secrets, "ui")),
    }
    assert zenoh_settings(RIDER, env)["transport/auth/usrpwd/password"] == f'"{lines["ui"]}"'
    assert len(set(lines.values())) == len(made)  # one password each

    again = procs.run_machine("credentials", "init", str(secrets))
    assert again.returncode == 1 and "exists already" in again.stderr
    assert (
        dict(line.split(":", 1) for line in (secrets / DICTIONARY).read_text().splitlines())
        == lines
    )

    # Exposed on every interface, but behind a login: no warning.
    proc, log = run_machine(
        tmp_path,
        "--zenoh-config",
        str(ACL_PROFILE),
        "--listen",
        f"tcp/0.0.0.0:{free_port()}",
        env={"MACHINE_ZENOH_DICTIONARY_FILE": str(secrets / DICTIONARY)},
    )
    try:
        text = wait_log(log, proc, "event=started")
    finally:
        stop_process(proc)
    assert WARNING not in text
    assert "event=acl_stations logins=gateway,ui" in text and "shared_login" not in text
