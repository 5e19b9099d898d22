"""Bad input from the rest of issue 15's list, each against real processes: hostile strings,
online writes the file check would flag, JSON in and out, simulator keys on hardware, a CLI
whose reader goes away, and command-line overrides that meet the file's checks."""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from ride_machine.rider.client import CommandRefused
from ride_machine.schema.codec import pack
from ride_machine.schema.commands import RotateStep, Session, StartRequest
from ride_machine.schema.errors import ErrorCode
from tests.fixtures.revpi import CONFIG_RSC, make_image
from tests.integration.support import module_machine
from tests.procs import (
    REPO,
    Daemon,
    free_port,
    machine_cmd,
    rider_cmd,
    run_machine,
    stop_process,
    wait_alive,
    write_zenoh_config,
)

pytestmark = pytest.mark.integration

HOSTILE = "evil\nstate       IDLE\x1b[2J\x00\u202eenod"
"""A session name that, printed raw, adds a fake `state` line, clears the screen and hides text."""

machine = module_machine("bad-input")


def raw_get(daemon: Daemon, key: str, payload: str) -> zenoh.Sample | zenoh.ReplyError:
    """One query as the zenoh CLI sends it: text, no encoding."""
    conf = zenoh.Config.from_file(str(daemon.zenoh_config))
    conf.insert_json5("connect/endpoints", json.dumps([daemon.endpoint]))
    with zenoh.open(conf) as session:
        for _ in range(20):  # the first query may go out before the machine's queryables arrive
            replies = list(session.get(key, payload=payload, timeout=2.0))
            if replies:
                reply = replies[0]
                return reply.ok if reply.ok is not None else reply.err  # type: ignore[return-value]
    raise AssertionError(f"no reply on {key}")


# ------------------------------------------------------------------------ hostile strings
@pytest.fixture
def fake_machine() -> Iterator[str]:
    """A process posing as machine `evil` whose status carries the hostile name; its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cmd = [sys.executable, "-m", "tests.reliability.forger", "--listen", endpoint]
    cmd += ["--machine-id", "evil", "--session-name", json.dumps(HOSTILE), "--duration", "60"]
    cmd += ["--token", "machine/evil/alive", "--queryable", "machine/evil/status"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("RIDER_ZENOH_")}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, cwd=REPO, env=env)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 20)
        assert ready and proc.stdout.readline().startswith("ready "), "fake machine did not start"
        yield endpoint
    finally:
        stop_process(proc)


@pytest.mark.hazard("H30")
def test_a_hostile_session_name_cannot_fake_a_status_line(fake_machine: str) -> None:
    done = subprocess.run(
        rider_cmd("--connect", fake_machine, "--machine", "evil", "status"),
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    labels = [line.split()[0] for line in lines]
    assert labels.count("state") == 1, done.stdout  # no second, fake `state` line
    assert labels == ["machine", "state", "calibrated", "home", "e-stop", "tilt", "rotate",
                      "session", "warning", "seq/uptime"]  # fmt: skip
    assert not any(c in done.stdout for c in "\x1b\x00\u202e")
    assert "evil\\nstate       IDLE\\x1b[2J\\x00\\u202eenod" in done.stdout  # shown, escaped
    as_json = subprocess.run(
        rider_cmd("--connect", fake_machine, "--machine", "evil", "--json", "status"),
        check=False, capture_output=True, text=True, timeout=60, cwd=REPO,
    )  # fmt: skip
    assert json.loads(as_json.stdout)["session"]["name"] == HOSTILE  # JSON stays faithful


@pytest.mark.hazard("H30")
def test_the_machine_refuses_a_session_name_that_is_not_printable(machine: Daemon) -> None:
    session = Session(name="x", steps=[RotateStep(revolutions=1)])
    with machine.rider() as r:
        request = StartRequest(transaction_id="hostile-name", session=session)
        data = request.model_dump(mode="json")
        data["session"]["name"] = HOSTILE
        with pytest.raises(CommandRefused) as refused:
            r.transport.get_one(f"{r.base}/cmd/start", pack(data), StartRequest, None)
    assert refused.value.error.code is ErrorCode.BAD_PAYLOAD
    assert refused.value.error.path == "/session/name"


# ------------------------------------------------------------ online writes, JSON in and out
@pytest.mark.hazard("H25")
def test_an_online_write_the_file_check_flags_is_refused(machine: Daemon) -> None:
    done = machine.cli("params", "set", "bus.heartbeat_s", "1e-9")
    assert done.returncode == 1, done.stdout
    assert "PARAM_OUT_OF_RANGE" in done.stderr and "cannot be held" in done.stderr
    shown = machine.cli("--json", "params", "get", "bus.heartbeat_s")
    assert json.loads(shown.stdout)["value"] == 0.2  # the fast config's, unchanged


def test_config_validate_answers_json_with_json(machine: Daemon) -> None:
    sample = raw_get(machine, "machine/m1/config/validate", '{"loop": {"period_s": 5}}')
    assert str(sample.encoding).startswith("application/json")
    findings = json.loads(sample.payload.to_bytes())
    assert findings["ok"] is False
    assert findings["findings"][0]["path"] == "/loop/period_s"


@pytest.mark.parametrize("scalar", ["42", '"home"', "true", "[1]"])
def test_a_json_scalar_is_reported_as_not_an_object(machine: Daemon, scalar: str) -> None:
    sample = raw_get(machine, "machine/m1/cmd/home", scalar)
    reply = json.loads(sample.payload.to_bytes())
    assert reply["error"]["code"] == "BAD_PAYLOAD"
    assert reply["error"]["message"].startswith("expected a JSON object"), reply
    assert "msgpack:" not in reply["error"]["message"]


# ---------------------------------------------------------------- sim/* on real hardware
def test_sim_keys_on_a_non_simulator_daemon_answer_not_available(tmp_path: Path) -> None:
    pytest.importorskip("revpimodio2")
    conf = tmp_path / "revpi.toml"
    conf.write_text(
        f'[hal]\nbackend = "revpi"\n[hal.revpi]\nprocimg = "{make_image(tmp_path)}"\n'
        f'configrsc = "{CONFIG_RSC}"\n'
    )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "revpi.log"
    cmd = machine_cmd("run", "--hal", "revpi", "--config", str(conf), "--listen", endpoint,
                      "--zenoh-config", str(write_zenoh_config(tmp_path)),
                      "--data-dir", str(tmp_path / "data"))  # fmt: skip
    with log.open("w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    daemon = Daemon(proc, endpoint, "m1", tmp_path / "data", tmp_path / "zenoh-test.json5", log)
    try:
        wait_alive(daemon)
    except BaseException:
        daemon.stop()
        raise
    try:
        done = daemon.cli("--timeout", "10", "sim", "estop")
        with daemon.rider(timeout=10) as r, pytest.raises(CommandRefused) as refused:
            r.sim("world")
    finally:
        daemon.stop()
    assert done.returncode == 1, done.stderr
    assert "NOT_AVAILABLE" in done.stderr and "revpi" in done.stderr
    assert refused.value.error.code is ErrorCode.NOT_AVAILABLE


# ------------------------------------------------------------------- the CLI's own output
def test_a_reader_that_goes_away_ends_the_cli_quietly(machine: Daemon) -> None:
    cmd = rider_cmd(
        "--connect", machine.endpoint, "--zenoh-config", str(machine.zenoh_config),
        "--machine", machine.machine_id, "watch", "--for", "20",
    )  # fmt: skip
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO
    )
    try:
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline()  # `| head -1`: one line, then the reader is gone
        proc.stdout.close()
        code = proc.wait(timeout=30)  # the next write fails; the CLI must end, not hang
        err = proc.stderr.read()
    finally:
        stop_process(proc)
    assert code == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err


@pytest.mark.hazard("H48")
@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--period", "0.5"], "--period: error: scan_period at /loop/period_s:"),
        (["--period", "0.0001"], "--period: error: out_of_range at /loop/period_s:"),
        (["--period", "fast"], "--period: error: wrong_type at /loop/period_s:"),
        (["--id", "a b"], "--id: error: out_of_range at /machine/id:"),
    ],
)
def test_bad_overrides_are_findings_and_do_not_start(
    tmp_path: Path, args: list[str], line: str
) -> None:
    data = tmp_path / "data"
    for command in ("run", "supervise"):
        run = subprocess.run(
            machine_cmd(command, "--sim", "--listen", f"tcp/127.0.0.1:{free_port()}",
                        "--data-dir", str(data), *args),
            check=False, capture_output=True, text=True, timeout=60, cwd=REPO,
        )  # fmt: skip
        assert run.returncode == 2, (command, run.stderr)
        assert line in run.stderr and "Traceback" not in run.stderr
        assert not data.exists()  # refused before anything opened
    validate = run_machine("validate", *args)
    assert validate.returncode == 2
    path = line.split(" at ")[1].rstrip(":")
    assert path in validate.stdout  # the same check, the same finding
