"""Talking to the daemon with tools that know nothing of this project: the `zenoh` CLI from the
`zenoh-cli` package, and a plain zenoh-python `get` as in its `examples/z_get.py`.

These are the commands docs/zenoh-cli.md shows; JSON in, JSON out.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ride_machine.schema.commands import Reply, ReplyCode
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.io import IoValue
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import STEP_TIMEOUT_S, module_machine, settle, states_over
from tests.procs import REPO, Daemon, run_bounded, stop_process

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(
        shutil.which("zenoh", path=str(Path(sys.executable).parent)) is None,
        reason="the `zenoh` command (pip install zenoh-cli) is not installed beside python",
    ),
]

ZENOH = str(Path(sys.executable).parent / "zenoh")
CLI_TIMEOUT_S = 30.0
BASE = "machine/m1"


machine = module_machine("zenoh-cli")


def zenoh_get(
    daemon: Daemon, selector: str, value: str | None = None
) -> subprocess.CompletedProcess[str]:
    """`zenoh --connect EP get -s SELECTOR [-v VALUE --encoder json] --decoder json`."""
    cmd = [ZENOH, "--connect", daemon.endpoint]
    # No multicast: only the daemon under test may answer, not others on this host.
    cmd += ["--cfg", "scouting/multicast/enabled:false", "get", "-s", selector]
    if value is not None:
        cmd += ["-v", value, "--encoder", "json"]
    cmd += ["--decoder", "json"]
    return subprocess.run(
        cmd, capture_output=True, text=True, timeout=CLI_TIMEOUT_S, cwd=REPO, check=False
    )


def replies(done: subprocess.CompletedProcess[str]) -> list[dict[str, Any]]:
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines() if line.strip()]


def test_status_as_json(machine: Daemon) -> None:
    (status,) = replies(zenoh_get(machine, f"{BASE}/status?format=json"))
    parsed = Status.model_validate(status)
    assert parsed.machine_id == "m1"
    assert status["state"] == parsed.state.value  # the state name as a plain string


def test_io_and_diag_as_json(machine: Daemon) -> None:
    points = [
        IoValue.model_validate(p) for p in replies(zenoh_get(machine, f"{BASE}/io/**?format=json"))
    ]
    assert {(p.kind, p.name) for p in points} >= {("ro", "rotateRelay"), ("di", "estop")}
    (diag,) = replies(zenoh_get(machine, f"{BASE}/diag/cycle?format=json"))
    assert CycleDiag.model_validate(diag).cycles > 0


def test_a_json_command_with_a_transaction_id_is_accepted_once(machine: Daemon) -> None:
    with machine.rider() as rider:
        (first,) = replies(
            zenoh_get(machine, f"{BASE}/cmd/calibrate/tilt", '{"transaction_id":"cli-cal-1"}')
        )
        reply = Reply.model_validate(first)
        assert reply.success and reply.code is ReplyCode.RESP_CALIBRATION_ACCEPTED
        assert reply.transaction_id == "cli-cal-1"
        assert settle(rider, reply).calibrated.tilt
        (again,) = replies(
            zenoh_get(machine, f"{BASE}/cmd/calibrate/tilt", '{"transaction_id":"cli-cal-1"}')
        )
        assert again == first
        states = {s.state for s in states_over(rider, 30)}
        assert MachineState.CALIBRATING not in states, "the repeat calibrated again"


def test_the_notice_and_the_calibration_from_the_cli(machine: Daemon) -> None:
    """docs/zenoh-cli.md: the timecode echo, `done/<id>` and `calibration` as JSON."""
    with machine.rider() as rider:
        request = '{"transaction_id":"cli-home-1","timecode":1795442745.5}'
        (first,) = replies(zenoh_get(machine, f"{BASE}/cmd/home", request))
        reply = Reply.model_validate(first)
        assert reply.request_timecode == 1795442745.5 and reply.timecode != 1795442745.5
        rider.wait_done(reply, STEP_TIMEOUT_S)
    (notice,) = replies(zenoh_get(machine, f"{BASE}/done/cli-home-1?format=json"))
    assert notice["transaction_id"] == "cli-home-1" and notice["command"] == "Home"
    assert notice["outcome"] in {"DONE", "FAULT_HW"}  # this module's machine may be uncalibrated
    (unknown,) = replies(zenoh_get(machine, f"{BASE}/done/never-1?format=json"))
    assert unknown["error"]["code"] == "UNKNOWN_TRANSACTION"
    (record,) = replies(zenoh_get(machine, f"{BASE}/calibration?format=json"))
    assert record["machine_id"] == "m1" and "complete" in record


def test_a_refused_command_replies_with_a_json_error(machine: Daemon) -> None:
    (unknown,) = replies(zenoh_get(machine, f"{BASE}/cmd/fly", '{"transaction_id":"cli-2"}'))
    error = Reply.model_validate(unknown).error
    assert error is not None and error.code is ErrorCode.UNKNOWN_COMMAND
    (bad,) = replies(
        zenoh_get(machine, f"{BASE}/cmd/start", '{"transaction_id":"cli-3","bogus":1}')
    )
    error = Reply.model_validate(bad).error
    assert error is not None and (error.code, error.path) == (ErrorCode.BAD_PAYLOAD, "/bogus")
    wildcard = zenoh_get(machine, f"{BASE}/cmd/*", '{"transaction_id":"cli-4"}')
    assert wildcard.stdout == ""  # an error reply: the CLI logs it instead of printing it
    assert "BAD_KEY" in wildcard.stderr


def test_sim_estop_from_the_cli(machine: Daemon) -> None:
    (pressed,) = replies(zenoh_get(machine, f"{BASE}/sim/estop", '{"pressed":true}'))
    assert SimWorldState.model_validate(pressed).estop_pressed
    with machine.rider() as rider:
        fault = rider.wait_for({MachineState.FAULT_ESTOP}, STEP_TIMEOUT_S)
        assert fault.estop.active
        (released,) = replies(zenoh_get(machine, f"{BASE}/sim/estop", '{"pressed":false}'))
        assert not SimWorldState.model_validate(released).estop_pressed
        (status,) = replies(zenoh_get(machine, f"{BASE}/status?format=json"))
        assert status["state"] == "FAULT_ESTOP"  # latched until Resume / Home / Stop
        (stop,) = replies(zenoh_get(machine, f"{BASE}/cmd/stop", '{"transaction_id":"cli-5"}'))
        assert Reply.model_validate(stop).code is ReplyCode.RESP_DONE


def test_a_plain_zenoh_python_get_like_z_get(machine: Daemon) -> None:
    """As `examples/z_get.py` does it: a string payload, no encoding, replies read as text."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([machine.endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        status = [
            r.ok.payload.to_string()
            for r in session.get(f"{BASE}/status?format=json", timeout=5.0)
            if r.ok is not None
        ]
        checked = [
            r.ok.payload.to_string()
            for r in session.get(
                f"{BASE}/cmd/check/calibration",
                target=zenoh.QueryTarget.BEST_MATCHING,
                payload='{"transaction_id": "zget-1"}',
                timeout=5.0,
            )
            if r.ok is not None
        ]
    assert Status.model_validate_json(status[0]).machine_id == "m1"
    reply = Reply.model_validate_json(checked[0])
    assert reply.code is ReplyCode.RESP_CHECK and reply.transaction_id == "zget-1"


# ------------------------------------------------------------- the project's msgpack codec
def zenoh_cli(daemon: Daemon, *args: str) -> list[str]:
    return [ZENOH, "--connect", daemon.endpoint, "--cfg", "scouting/multicast/enabled:false", *args]


def test_msgpack_decoder_reads_replies_without_format_json(machine: Daemon) -> None:
    """The plugin (rider/zenoh_codec.py, an entry point of the package) reads msgpack replies."""
    done = run_bounded(
        zenoh_cli(machine, "get", "-s", f"{BASE}/status", "--decoder", "msgpack"), CLI_TIMEOUT_S
    )
    (status,) = replies(done)
    assert Status.model_validate(status).machine_id == "m1"


def test_msgpack_encoder_sends_a_command_the_machine_reads(machine: Daemon) -> None:
    done = run_bounded(
        zenoh_cli(
            machine,
            "get",
            "-s",
            f"{BASE}/cmd/check/home",
            "-v",
            '{"transaction_id":"cli-mp-1"}',
            "--encoder",
            "msgpack",
            "--decoder",
            "msgpack",
        ),
        CLI_TIMEOUT_S,
    )
    (reply,) = replies(done)
    parsed = Reply.model_validate(reply)
    assert parsed.transaction_id == "cli-mp-1" and parsed.code is ReplyCode.RESP_CHECK


def test_msgpack_decoder_prints_live_samples_as_json(machine: Daemon) -> None:
    """`zenoh subscribe -k 'machine/**' --decoder msgpack`: every live key as a JSON line."""
    proc = subprocess.Popen(
        zenoh_cli(
            machine,
            "subscribe",
            "-k",
            "machine/**",
            "--decoder",
            "msgpack",
            "--line",
            "{key} {value}",
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    seen: dict[str, dict[str, Any]] = {}
    try:
        assert proc.stdout is not None
        # The status heartbeat (1 s) and diag/cycle (1 Hz) come by themselves; the line count
        # bounds the loop, the test timeout bounds a silent CLI.
        for _, line in zip(range(200), proc.stdout, strict=False):
            key, _, value = line.strip().partition(" ")
            seen[key] = json.loads(value)
            if {f"{BASE}/status", f"{BASE}/diag/cycle"} <= seen.keys():
                break
    finally:
        stop_process(proc)
    assert Status.model_validate(seen[f"{BASE}/status"]).machine_id == "m1"
    assert CycleDiag.model_validate(seen[f"{BASE}/diag/cycle"]).cycles > 0
