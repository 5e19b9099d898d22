"""A Rider in its own process, for tests that need one: it runs steps and reports JSON lines.

    python -m tests.integration.rider_proc --connect tcp/10.0.0.1:7447 alive prepare start done

Steps: `alive` (wait for the machine's first published status), `prepare` (calibrate + home),
`start` (the default session, or `--revolutions N` at 45°, with this process as the
supervising Rider), `running` (wait
for the first revolution), `done` (wait for DONE), `hold` (report, then block until killed or
stdin closes). Each step prints `{"step": ..., "status": ...}`; `done` adds the simulated
world's revolutions travelled since `start`. Exit code 0, or 1 with `{"error": ...}`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import queue
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh

from ride_machine.rider.client import Rider, RiderError
from ride_machine.schema.codec import Format, decode
from ride_machine.schema.commands import Reply, RotateStep, Session, TiltStep
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import (
    SETTLED,
    STEP_TIMEOUT_S,
    Preparation,
    relays_off,
    until_revolutions,
)
from tests.procs import REPO, Daemon

STEPS = ("alive", "prepare", "start", "running", "done", "hold")


def command(endpoint: str, zenoh_config: Path, machine_id: str, *args: str) -> list[str]:
    """The command line that runs this module as its own process."""
    me = [sys.executable, "-m", "tests.integration.rider_proc", "--connect", endpoint]
    return [*me, "--zenoh-config", str(zenoh_config), "--machine", machine_id, *args]


def read_step(proc: subprocess.Popen[str], step: str) -> dict[str, Any]:
    """This module's report for `step`, read from a child running it (bounded by its own
    step timeouts); an `error` report fails the caller."""
    assert proc.stdout is not None
    for line in proc.stdout:
        record: dict[str, Any] = json.loads(line)
        assert "error" not in record, record["error"]
        if record["step"] == step:
            return record
    raise AssertionError(f"rider process ended (code {proc.wait(5)}) before step {step}")


@contextlib.contextmanager
def supervising(
    daemon: Daemon, env: Mapping[str, str] | None = None, revolutions: int = 40
) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """A Rider in its own process (with `env` as its environment, else this one's) that
    prepares the machine, starts a session of `revolutions` and holds it mid-ride: its process
    and its Rider id; killed at the end whatever happens."""
    cmd = command(daemon.endpoint, daemon.zenoh_config, daemon.machine_id)
    cmd += ["--revolutions", str(revolutions), "prepare", "start", "running", "hold"]
    proc = subprocess.Popen(
        cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO, env=env
    )
    try:
        yield proc, read_step(proc, "hold")["rider"]
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(STEP_TIMEOUT_S)


def kill_until_paused(
    proc: subprocess.Popen[str], observer: Rider, bound: float
) -> tuple[Status, float]:
    """SIGKILL a supervising Rider; the PAUSED status that follows (within `bound` seconds)
    and how long it took."""
    killed_at = time.monotonic()
    proc.send_signal(signal.SIGKILL)
    proc.wait(STEP_TIMEOUT_S)
    paused = observer.wait_for({MachineState.PAUSED}, bound)
    return paused, time.monotonic() - killed_at


def assert_loss_pauses(
    proc: subprocess.Popen[str], observer: Rider, bound: float, what: str
) -> Status:
    """The supervising Rider `proc` SIGKILLed mid-ride: the machine goes from RUNNING to
    PAUSED within `bound`, its Rider gone and every relay off. Prints how long it took."""
    assert observer.status().state is MachineState.RUNNING
    paused, took = kill_until_paused(proc, observer, bound)
    print(f"{what}: killed -> PAUSED in {took:.2f} s")
    assert paused.previous_state is MachineState.RUNNING
    assert not paused.rider_connected
    assert relays_off(observer)
    return paused


def report(step: str, **fields: Any) -> None:
    print(json.dumps({"step": step, "time": time.time(), **fields}), flush=True)


def wait_alive(rider: Rider, timeout: float) -> Status:
    """The machine's first published status (a heartbeat comes every 0.2 s at the fast config).

    A sample, unlike the liveliness token, proves the machine's declarations have reached this
    session: its queryables answer the queries that follow even while it is still starting.
    """
    samples: queue.Queue[zenoh.Sample] = queue.Queue()
    sub = rider.session.declare_subscriber(f"{rider.base}/status", samples.put)
    try:
        sample = samples.get(timeout=timeout)
    except queue.Empty:
        raise RiderError(f"no status from {rider.base} within {timeout:g} s") from None
    finally:
        sub.undeclare()
    return decode(Status, sample.payload.to_bytes(), Format.MSGPACK)


def run(rider: Rider, steps: Sequence[str], revolutions: int | None) -> None:
    revolutions_at_start = 0.0
    started: Reply | None = None
    ready = Preparation(rider)
    session = None
    if revolutions is not None:
        session = Session(
            name=f"{revolutions} revolutions",
            steps=[TiltStep(degrees=45.0), RotateStep(revolutions=revolutions)],
        )
    for step in steps:
        if step == "alive":
            report(step, status=wait_alive(rider, STEP_TIMEOUT_S).model_dump(mode="json"))
        elif step == "prepare":
            report(step, status=ready.prepare().model_dump(mode="json"))
        elif step == "start":
            revolutions_at_start = rider.sim("world").revolutions
            started = rider.start(session)
            report(step, reply=started.model_dump(mode="json"), rider=rider.rider_id)
        elif step == "running":
            if started is None:
                raise RiderError("`running` needs `start` first")
            # A fault the loaded host caused (the supervised world late) rides again.
            started, status = ready.ride(
                lambda: rider.start(session),
                lambda reply: until_revolutions(rider, reply, 1),
                started=started,
            )
            assert status.state not in SETTLED, f"session ended early: {status}"
            report(step, status=status.model_dump(mode="json"))
        elif step == "done":
            final = rider.wait_for({MachineState.DONE}, STEP_TIMEOUT_S)
            world = rider.sim("world")
            report(
                step,
                status=final.model_dump(mode="json"),
                world=world.model_dump(mode="json"),
                revolutions=world.revolutions - revolutions_at_start,
            )
        elif step == "hold":
            report(step, rider=rider.rider_id)
            sys.stdin.read()


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="rider_proc", description=__doc__)
    p.add_argument("--connect", action="append", required=True)
    p.add_argument("--zenoh-config", type=Path)
    p.add_argument("--machine", default="m1")
    p.add_argument("--revolutions", type=int, help="session length (default: the default session)")
    p.add_argument("steps", nargs="+", choices=STEPS)
    args = p.parse_args(argv)
    try:
        with Rider(
            args.machine, connect=args.connect, zenoh_config_path=args.zenoh_config
        ) as rider:
            run(rider, args.steps, args.revolutions)
    except (RiderError, AssertionError) as exc:
        print(json.dumps({"error": f"{type(exc).__name__}: {exc}"}), flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
