"""The `rider` command as scripts use it: subprocesses, --json output and exit codes.

Exit codes: 0 done, 1 refused (or the motion ended in a fault), 2 bad usage, 3 no reply,
4 several machines alive and none named.
"""

from __future__ import annotations

import json
import queue
import subprocess
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ride_machine.rider.client import Rider
from ride_machine.schema.commands import Reply, ReplyCode
from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.io import IoValue
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import STEP_TIMEOUT_S, fast_daemon, module_machine, prepare
from tests.procs import REPO, Daemon, free_port, rider_cmd

pytestmark = pytest.mark.integration

CLI_TIMEOUT_S = 30.0
OK, REFUSED, USAGE, NO_REPLY, AMBIGUOUS = 0, 1, 2, 3, 4


machine = module_machine("cli")


def args_for(daemon: Daemon, *args: str) -> list[str]:
    return rider_cmd(
        "--connect", daemon.endpoint, "--zenoh-config", str(daemon.zenoh_config), *args
    )


def rider(daemon: Daemon, *args: str) -> subprocess.CompletedProcess[str]:
    """Run `rider …` against `daemon`, bounded."""
    return daemon.run_rider(*args, timeout=CLI_TIMEOUT_S)


def background(daemon: Daemon, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(args_for(daemon, *args), stdout=subprocess.PIPE, text=True, cwd=REPO)


def json_lines(out: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in out.splitlines() if line.strip()]


def ok_json(done: subprocess.CompletedProcess[str]) -> list[dict[str, Any]]:
    assert done.returncode == OK, f"exit {done.returncode}: {done.stderr}"
    return json_lines(done.stdout)


WATCH_UNTIL = ("--json", "watch", "--keys", "status", "--for", str(STEP_TIMEOUT_S), "--until")
"""`rider … STATE`: watch the status until the machine is in STATE (bounded)."""


def wait_state(daemon: Daemon, state: MachineState) -> Status:
    """`rider watch --until STATE`; its last line is the status it stopped on."""
    done = rider(daemon, *WATCH_UNTIL, state.value)
    last = Status.model_validate(ok_json(done)[-1])
    assert last.state is state
    return last


def finish(proc: subprocess.Popen[str]) -> tuple[int, list[dict[str, Any]]]:
    try:
        out, _ = proc.communicate(timeout=CLI_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(CLI_TIMEOUT_S)
    return proc.returncode, json_lines(out)


@pytest.fixture
def long_session(tmp_path: Path) -> Path:
    path = tmp_path / "long.json"
    steps = [{"kind": "tilt", "degrees": 30}, {"kind": "rotate", "revolutions": 40}]
    path.write_text(json.dumps({"name": "long", "steps": steps}))
    return path


def test_a_whole_session_from_the_cli_with_json_output(machine: Daemon) -> None:
    # `--wait` prints the reply, the completion notice of that transaction, the status after.
    for axis in ("tilt", "rotate"):
        reply, notice, status = ok_json(rider(machine, "--json", "calibrate", axis, "--wait"))
        assert Reply.model_validate(reply).code is ReplyCode.RESP_CALIBRATION_ACCEPTED
        assert Completion.model_validate(notice).outcome is Outcome.DONE
        assert notice["transaction_id"] == reply["transaction_id"]
        assert getattr(Status.model_validate(status).calibrated, axis)
    reply, notice, status = ok_json(rider(machine, "--json", "home", "--wait"))
    assert Reply.model_validate(reply).code is ReplyCode.RESP_HOME_ACCEPTED
    assert (notice["command"], notice["outcome"]) == ("Home", "DONE")
    assert Status.model_validate(status).state is MachineState.IDLE
    check = ok_json(rider(machine, "--json", "check", "calibration"))[0]
    assert check == {"ok": True, "tilt": True, "rotate": True}

    watcher = background(machine, *WATCH_UNTIL, "DONE")
    assert watcher.stdout is not None
    Status.model_validate_json(watcher.stdout.readline())  # subscribed: it printed the current
    reply, notice, final = ok_json(rider(machine, "--json", "start", "--wait"))
    assert Reply.model_validate(reply).code is ReplyCode.RESP_START_ACCEPTED
    assert (notice["outcome"], notice["state"]) == ("DONE", "DONE")
    late = ok_json(rider(machine, "--json", "done", reply["transaction_id"]))[0]
    assert late == notice  # a late Rider learns how it ended
    done = Status.model_validate(final)
    assert done.state is MachineState.DONE
    assert done.session is not None and done.session.revolutions_done == 3

    code, watched = finish(watcher)
    assert code == OK
    states = [Status.model_validate(s).state for s in watched]
    assert MachineState.RUNNING in states and states[-1] is MachineState.DONE

    status = Status.model_validate(ok_json(rider(machine, "--json", "status"))[0])
    assert status.state is MachineState.DONE
    points = [IoValue.model_validate(p) for p in ok_json(rider(machine, "--json", "io"))[0]]
    assert {p.name for p in points} >= {"rotateRelay", "tiltRelay", "estop"}
    assert not any(p.value for p in points if p.kind == "ro")
    diag = CycleDiag.model_validate(ok_json(rider(machine, "--json", "diag"))[0])
    assert diag.cycles > 0
    # Tilt stands at 45°, not at home: the check answers, and says no with exit code 1.
    not_home = rider(machine, "--json", "check", "home")
    assert not_home.returncode == REFUSED
    assert json.loads(not_home.stdout)["ok"] is False


def test_pause_resume_stop_and_estop_from_the_cli(machine: Daemon, long_session: Path) -> None:
    with machine.rider() as setup:
        prepare(setup)
    running = background(machine, "--json", "start", "--session", str(long_session), "--wait")
    try:
        wait_state(machine, MachineState.RUNNING)
        paused = Reply.model_validate(ok_json(rider(machine, "--json", "pause"))[0])
        assert paused.code is ReplyCode.RESP_PAUSED
        wait_state(machine, MachineState.PAUSED)
        world = SimWorldState.model_validate(ok_json(rider(machine, "--json", "sim", "world"))[0])
        assert not any(world.relays.values())
        resumed = Reply.model_validate(ok_json(rider(machine, "--json", "resume"))[0])
        assert resumed.code is ReplyCode.RESP_RESUMED

        ok_json(rider(machine, "--json", "sim", "estop"))
        fault = wait_state(machine, MachineState.FAULT_ESTOP)
        assert fault.estop.latched

        refused = rider(machine, "--json", "start")
        assert refused.returncode == REFUSED
        error = Reply.model_validate_json(refused.stdout).error
        assert error is not None and error.code is ErrorCode.ESTOP_ACTIVE
        assert "refused" in refused.stderr

        # An E-stopped session is not over: `start --wait` still waits for its notice.
        assert running.poll() is None
        ok_json(rider(machine, "--json", "sim", "release"))
        reply, final = ok_json(rider(machine, "--json", "stop", "--wait"))
        assert Reply.model_validate(reply).code is ReplyCode.RESP_DONE
        assert Status.model_validate(final).state is MachineState.DONE
        # The Stop ended it: exit 1 (not DONE), the notice says STOPPED after an E-stop.
        code, lines = finish(running)
        assert code == REFUSED
        notice = Completion.model_validate(lines[-2])
        assert notice.outcome is Outcome.STOPPED and "after an E-stop" in notice.reason
        assert Status.model_validate(lines[-1]).state is MachineState.DONE
    finally:
        if running.poll() is None:
            running.kill()
            running.wait(CLI_TIMEOUT_S)
    world = SimWorldState.model_validate(ok_json(rider(machine, "--json", "sim", "world"))[0])
    assert not world.estop_pressed and not any(world.relays.values())


def test_a_refused_command_exits_1_with_the_error_as_json(machine: Daemon) -> None:
    done = rider(machine, "--json", "pause")
    assert done.returncode == REFUSED
    reply = Reply.model_validate_json(done.stdout)
    assert not reply.success
    assert reply.error is not None and reply.error.code is ErrorCode.WRONG_STATE
    assert reply.error.message in done.stderr


def test_no_machine_exits_3(machine: Daemon) -> None:
    nobody = f"tcp/127.0.0.1:{free_port()}"
    for extra in (["-m", "m1"], []):
        done = subprocess.run(
            rider_cmd(
                "--connect",
                nobody,
                "--zenoh-config",
                str(machine.zenoh_config),
                "--timeout",
                "0.5",
                *extra,
                "status",
            ),
            capture_output=True,
            text=True,
            timeout=CLI_TIMEOUT_S,
            cwd=REPO,
            check=False,
        )
        assert done.returncode == NO_REPLY, done.stderr
        assert done.stderr.startswith("rider: ")


def test_bad_usage_exits_2(machine: Daemon, tmp_path: Path) -> None:
    missing = rider(machine, "start", "--session", str(tmp_path / "nope.json"))
    assert missing.returncode == USAGE
    assert "cannot read" in missing.stderr
    bad = tmp_path / "bad.json"
    bad.write_text('{"steps": [{"kind": "tilt", "degrees": "steep"}]}')
    invalid = rider(machine, "start", "--session", str(bad))
    assert invalid.returncode == USAGE
    assert "not a valid session" in invalid.stderr


@pytest.mark.hazard("H37")
def test_two_machines_and_none_named_exits_4(machine: Daemon, tmp_path: Path) -> None:
    with fast_daemon(tmp_path, "m2") as other:
        both = ["--connect", other.endpoint]
        ambiguous = rider(machine, *both, "status")
        assert ambiguous.returncode == AMBIGUOUS
        assert "m1" in ambiguous.stderr and "m2" in ambiguous.stderr
        named = Status.model_validate(
            ok_json(rider(machine, *both, "-m", "m2", "--json", "status"))[0]
        )
        assert named.machine_id == "m2"


def test_watch_until_waits_through_a_quiet_spell(tmp_path: Path) -> None:
    """`watch --until` keeps waiting while nothing is published (here: a 10 s heartbeat)."""
    with fast_daemon(tmp_path, heartbeat_s=10.0) as quiet:
        watcher = background(quiet, *WATCH_UNTIL, "CALIBRATING")
        try:
            assert watcher.stdout is not None
            first = Status.model_validate_json(watcher.stdout.readline())
            assert first.state is MachineState.WARNING_NEEDS_CALIBRATION
            with quiet.rider(supervise=False) as rider:
                diag_samples(rider, 3)  # over a second in which no status is published
                rider.calibrate_tilt()
            code, lines = finish(watcher)
        finally:
            if watcher.poll() is None:
                watcher.kill()
                watcher.wait(CLI_TIMEOUT_S)
        assert code == OK, lines
        assert Status.model_validate(lines[-1]).state is MachineState.CALIBRATING


def diag_samples(rider: Rider, count: int) -> None:
    """Wait for `count` publications of diag/cycle (one every 0.5 s in the fast config)."""
    samples: queue.Queue[zenoh.Sample] = queue.Queue()
    sub = rider.session.declare_subscriber(f"{rider.base}/diag/cycle", samples.put)
    try:
        for _ in range(count):
            samples.get(timeout=STEP_TIMEOUT_S)
    finally:
        sub.undeclare()


def test_sim_prints_the_world_in_a_few_lines(tmp_path: Path) -> None:
    """Issue 57, reproduction 7: `rider sim estop` printed the world as 30 lines of JSON; a line
    per part now (`--json` keeps every field)."""
    with fast_daemon(tmp_path) as daemon:
        pressed = rider(daemon, "sim", "estop")
        assert pressed.returncode == OK, pressed.stderr
        lines = pressed.stdout.splitlines()
        assert len(lines) <= 8 and not any("{" in line for line in lines), pressed.stdout
        assert lines[0].split() == ["world", "E-stop", "pressed,", "no", "charge", "pump"]
        assert any(line.startswith("relays") and "all off" in line for line in lines), lines
        released = rider(daemon, "sim", "release")
        assert released.stdout.splitlines()[0].startswith("world      E-stop released")
        full = SimWorldState.model_validate(ok_json(rider(daemon, "--json", "sim", "world"))[0])
        assert not full.estop_pressed
