"""Completion notices through real Zenoh: a Rider waits on its own transaction, a late Rider
asks how it ended, a raw subscriber sees exactly one notice, the seed's refused Start."""

from __future__ import annotations

import json
import queue
import subprocess
import threading
import time

import pytest
import zenoh

from ride_machine.rider.client import UnknownTransaction
from ride_machine.schema.codec import Format, decode
from ride_machine.schema.commands import Command, Session
from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import STEP_TIMEOUT_S, module_machine, prepare
from tests.procs import REPO, Daemon, rider_cmd

pytestmark = pytest.mark.integration

machine = module_machine("completion")

LONG = Session.model_validate(
    {
        "name": "long",
        "steps": [{"kind": "tilt", "degrees": 20}, {"kind": "rotate", "revolutions": 40}],
    }
)


def raw_notices(daemon: Daemon, key: str) -> tuple[zenoh.Session, queue.Queue[Completion]]:
    """A plain zenoh-python subscriber (not the Rider library) on `key`."""
    conf = zenoh.Config.from_file(str(daemon.zenoh_config))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", f'["{daemon.endpoint}"]')
    session = zenoh.open(conf)
    got: queue.Queue[Completion] = queue.Queue()
    session.declare_subscriber(
        key, lambda s: got.put(decode(Completion, s.payload.to_bytes(), Format.MSGPACK))
    )
    return session, got


def mine(heard: queue.Queue[Completion], tid: str, timeout: float = 5.0) -> Completion:
    """The first notice heard for `tid` (bounded); notices of earlier transactions skipped."""
    deadline = time.monotonic() + timeout
    while (got := heard.get(timeout=max(deadline - time.monotonic(), 0.01))).transaction_id != tid:
        pass
    return got


def drained(heard: queue.Queue[Completion]) -> list[Completion]:
    out = []
    while not heard.empty():
        out.append(heard.get_nowait())
    return out


def test_home_notice_reaches_the_waiting_rider_a_raw_subscriber_and_a_late_rider(
    machine: Daemon,
) -> None:
    with machine.rider() as r:
        prepare(r)
        session, heard = raw_notices(machine, f"{r.base}/done/**")
        try:
            reply = r.home()
            notice = r.wait_done(reply, timeout=STEP_TIMEOUT_S)
            assert notice.transaction_id == reply.transaction_id
            assert (notice.command, notice.outcome, notice.state) == (
                "Home",
                Outcome.DONE,
                MachineState.IDLE,
            )
            # The preparation's own last notice may still be on its way to the new subscriber.
            assert mine(heard, reply.transaction_id) == notice
            assert r.status().motion is None
        finally:
            session.close()
        assert all(n.transaction_id != reply.transaction_id for n in drained(heard))  # just one
    with machine.rider() as late:
        assert late.done(reply.transaction_id) == notice
        assert notice in late.recent_completions()
        with pytest.raises(UnknownTransaction):
            late.done("never-sent-1")


def test_a_session_is_in_progress_until_its_notice_and_stop_ends_it_stopped(
    machine: Daemon,
) -> None:
    with machine.rider() as r:
        prepare(r)
        reply = r.start(LONG)
        assert r.done(reply) is None  # in progress: no notice yet
        motion = r.wait_for({MachineState.RUNNING}, STEP_TIMEOUT_S, after=reply.timecode).motion
        assert motion is not None and motion.transaction_id == reply.transaction_id
        got: list[Completion] = []
        waiter = threading.Thread(
            target=lambda: got.append(r.wait_done(reply, timeout=STEP_TIMEOUT_S))
        )
        waiter.start()
        r.pause()
        r.resume()
        r.stop()
        waiter.join(STEP_TIMEOUT_S)
        assert got and got[0].outcome is Outcome.STOPPED
        assert got[0].state is MachineState.DONE


def test_a_start_refused_for_home_sends_the_warning_then_its_notice(machine: Daemon) -> None:
    with machine.rider() as r:
        prepare(r)
        tilted = r.start(Session.model_validate({"steps": [{"kind": "tilt", "degrees": 10}]}))
        assert r.wait_done(tilted, timeout=STEP_TIMEOUT_S).outcome is Outcome.DONE
        seen: queue.Queue[Status | Completion] = queue.Queue()
        with r.subscribe(["status", "done/**"], seen.put):
            # Subscriptions reach the machine asynchronously: one heartbeat proves they have.
            assert isinstance(seen.get(timeout=5.0), Status)
            refused = r.command(Command.START, check=False)  # the tilt is not home
            notice = r.wait_done(refused, timeout=STEP_TIMEOUT_S)
            order: list[str] = []
            while True:
                item = seen.get(timeout=5.0)
                if isinstance(item, Status):
                    order.append(item.state.value)
                elif item.transaction_id == refused.transaction_id:
                    order.append("notice")
                    break
        assert not refused.success and refused.error is not None
        assert refused.error.code == "NOT_HOME"
        assert (notice.outcome, notice.code) == (Outcome.REFUSED, "NOT_HOME")
        assert order[-2:] == [MachineState.WARNING_NOT_HOME.value, "notice"]


def test_wait_done_on_an_unknown_transaction_raises_at_once(machine: Daemon) -> None:
    with machine.rider() as r, pytest.raises(UnknownTransaction):
        r.wait_done("nobody-sent-this", timeout=STEP_TIMEOUT_S)


def test_resume_wait_waits_for_the_notice_of_the_motion_it_resumes(machine: Daemon) -> None:
    with machine.rider() as r:
        prepare(r)
        reply = r.start(Session.model_validate({"steps": [{"kind": "rotate", "revolutions": 2}]}))
        r.pause()
        done = subprocess.run(
            rider_cmd(
                "--connect", machine.endpoint, "--zenoh-config", str(machine.zenoh_config),
                "--json", "resume", "--wait",
            ),
            capture_output=True, text=True, timeout=STEP_TIMEOUT_S + 10, cwd=REPO, check=False,
        )  # fmt: skip
    assert done.returncode == 0, done.stderr
    resumed, notice, status = (json.loads(line) for line in done.stdout.splitlines())
    assert resumed["code"] == "RESP_RESUMED"
    assert notice["transaction_id"] == reply.transaction_id and notice["outcome"] == "DONE"
    assert status["state"] == "DONE" and status["motion"] is None
