"""The event history end to end: real daemons through sessions, an E-stop, a fault and restarts,
read back with `rider events` (a subprocess), followed live, and queried raw over Zenoh."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ride_machine.rider.client import Rider
from ride_machine.schema.codec import Format, decode
from ride_machine.schema.events import Event, EventPage, EventQuery
from ride_machine.schema.status import MachineState, Status
from ride_machine.service.adapters.eventlog import EVENTS_FILE
from tests.integration.support import fast_args, one_reply, prepare, settle
from tests.procs import (
    REPO,
    Daemon,
    rider_cmd,
    run_machine,
    start_daemon,
    stop_process,
)

pytestmark = pytest.mark.integration

CLI_TIMEOUT_S = 30.0
S = MachineState

FIRST_RUN = [
    "daemon_start",
    # CalibrateTilt, CalibrateRotate: the new values are in use (and being written) while
    # the state stays CALIBRATING until the write is done; the calibration is recorded once
    # the write has ended, saying how it went (issue 37); then Home
    *["command", "state", "state", "completion", "calibration"] * 2,
    *["command", "state", "state", "completion"],
    # the default session, to DONE
    *["command", "state", "session_started", "state", "session_ended", "completion"],
    # E-stop pressed and released in DONE, then Home resets the latch and re-homes
    *["estop_pressed", "state", "estop_latched", "estop_released"],
    *["command", "state", "estop_reset", "state", "completion"],
    # a session into a stalled tilt: FAULT_HW
    *["command", "state", "session_started", "state", "fault_raised", "session_ended"],
    "completion",
    # a refused command, then a parameter write
    "command",
    "param_changed",
    "daemon_stop",
]


def rider_cli(daemon: Daemon, *args: str) -> subprocess.CompletedProcess[str]:
    return daemon.run_rider(*args, timeout=CLI_TIMEOUT_S)


def cli_events(daemon: Daemon, *args: str) -> list[dict[str, Any]]:
    out = rider_cli(daemon, "events", "--json", *args)
    assert out.returncode == 0, out.stderr
    return [json.loads(line) for line in out.stdout.splitlines() if line.strip()]


def raw_page(daemon: Daemon, selector: str) -> EventPage:
    """A plain zenoh-python query, JSON asked for in the selector, as any client could."""
    conf = zenoh.Config.from_file(str(daemon.zenoh_config))
    conf.insert_json5("connect/endpoints", json.dumps([daemon.endpoint]))
    with zenoh.open(conf) as session:
        sample = one_reply(session, selector)
        assert str(sample.encoding).startswith("application/json")
        return EventPage.model_validate_json(sample.payload.to_bytes())


def drive_first_run(r: Rider) -> None:
    prepare(r)
    settle(r, r.start())
    r.sim("estop", pressed=True)
    r.wait_for({S.FAULT_ESTOP}, 10.0)
    r.sim("estop", pressed=False)
    # Home is refused until the scan loop has seen the release: wait for it in the status.
    released = next(
        u for u in r.watch(("status",), timeout=5.0) if isinstance(u, Status) and not u.estop.active
    )
    assert released.state is S.FAULT_ESTOP
    assert settle(r, r.home()).state is S.IDLE
    r.sim("stall", axis="tilt", stalled=True)
    assert settle(r, r.start()).state is S.FAULT_HW
    r.sim("clear")


def first_run_followed(tmp_path: Path, extra: list[str]) -> list[dict[str, Any]]:
    """The first run (`drive_first_run`, a refused Pause, a parameter write, a clean stop) with
    `rider events --follow` beside it; what the follower saw."""
    daemon = start_daemon(tmp_path, extra=extra)
    follow = Follower(daemon)
    try:
        with daemon.rider(supervise=False) as r:
            drive_first_run(r)
            refused = rider_cli(daemon, "pause")
            assert refused.returncode == 1
            r.set_param("tilt.tolerance_deg", 1.5)
            # The follower has seen the parameter write: it follows live.
            assert follow.wait_for("param_changed")
        assert daemon.stop() == 0
        assert follow.wait_for("daemon_stop")
    finally:
        followed = follow.stop()
        daemon.stop(signal.SIGKILL)
    return followed


def test_a_ride_its_faults_and_restarts_read_back_exactly(tmp_path: Path) -> None:
    extra = fast_args(tmp_path)
    followed = first_run_followed(tmp_path, extra)

    # A restart (clean), then a kill and another restart on the same data_dir.
    daemon = start_daemon(tmp_path, extra=extra)
    daemon.stop(signal.SIGKILL)
    daemon = start_daemon(tmp_path, extra=extra)
    try:
        everything = cli_events(daemon, "--since", "1")
        assert [e["seq"] for e in everything] == list(range(1, len(everything) + 1))
        # A command retried after a reply timeout (a loaded host) is recorded again as a
        # repeat: real, but not part of the ride's story.
        events = [e for e in everything if not e["details"].get("repeat")]
        kinds = [e["kind"] for e in events]
        assert kinds == [*FIRST_RUN, "daemon_start", "daemon_start"], kinds
        starts = [e["details"] for e in events if e["kind"] == "daemon_start"]
        assert [s["previous_stop_clean"] for s in starts] == [None, True, False]
        stop = next(e["details"] for e in events if e["kind"] == "daemon_stop")
        assert stop == {"kind": "daemon_stop", "reason": "signal SIGTERM", "exit_code": 0}
        _check_details(events)

        # The live follower saw the same events with the same seq numbers, up to the stop.
        assert followed == everything[: len(followed)]
        assert followed[-1]["kind"] == "daemon_stop"

        # A raw Zenoh query returns the same events; a kind filter and paging work there too.
        page = raw_page(daemon, "machine/m1/events?since=1;format=json")
        assert [e.model_dump(mode="json") for e in page.events] == everything
        faults = raw_page(daemon, "machine/m1/events?kind=fault_raised;format=json").events
        assert [e.details.code for e in faults] == ["TILT_NOT_FOLLOWING"]  # type: ignore[union-attr]
        first = raw_page(daemon, "machine/m1/events?limit=5;format=json")
        assert (len(first.events), first.more, first.next_since) == (5, True, 6)

        # The summary counts what happened.
        out = rider_cli(daemon, "--json", "events", "--summary", "--since", "1d")
        assert out.returncode == 0, out.stderr
        [summary] = json.loads(out.stdout)
        assert summary["sessions_started"] == 2
        assert (summary["sessions_done"], summary["sessions_faulted"]) == (1, 1)
        assert summary["estops"] == 1
        assert summary["faults_by_code"] == {"TILT_NOT_FOLLOWING": 1}
        assert (summary["daemon_starts"], summary["unclean_stops"]) == (3, 1)
        assert summary["ride_time_s"] > 0

        # Offline: the export reads the database file itself.
        export = run_machine(
            *("events", "export", "--data-dir", str(daemon.data_dir)),
            *("--format", "jsonl", "--kind", "session_ended"),
            timeout=CLI_TIMEOUT_S,
        )
        assert export.returncode == 0, export.stderr
        ended = [Event.model_validate_json(line) for line in export.stdout.splitlines()]
        assert [e.details.outcome for e in ended] == ["DONE", "FAULT_HW"]  # type: ignore[union-attr]
        assert (daemon.data_dir / EVENTS_FILE).is_file()
    finally:
        daemon.stop()


def _check_details(events: list[dict[str, Any]]) -> None:
    """Who asked, and what the commands and the fault were."""
    commands = [e["details"] for e in events if e["kind"] == "command"]
    assert [c["command"] for c in commands] == [
        "CalibrateTilt",
        "CalibrateRotate",
        "Home",
        "Start",
        "Home",
        "Start",
        "Pause",
    ]
    assert all(c["rider"] for c in commands)  # the sender's session id, even one-shot
    assert len({c["rider"] for c in commands}) == 2  # the test's Rider and the `rider pause`
    assert [c["accepted"] for c in commands] == [True] * 6 + [False]
    assert commands[-1]["code"] == "WRONG_STATE"
    completions = [e["details"] for e in events if e["kind"] == "completion"]
    tx = [c["transaction_id"] for c in commands if c["command"] != "Pause"]
    assert [c["transaction_id"] for c in completions] == tx
    assert [c["outcome"] for c in completions] == ["DONE"] * 5 + ["FAULT_HW"]
    param = next(e["details"] for e in events if e["kind"] == "param_changed")
    assert (param["name"], param["old"], param["new"]) == ("tilt.tolerance_deg", 1.0, 1.5)


class Follower:
    """`rider events --follow --json` in its own process; a thread collects its lines."""

    def __init__(self, daemon: Daemon) -> None:
        cmd = rider_cmd("--connect", daemon.endpoint, "--zenoh-config", str(daemon.zenoh_config))
        self.proc = subprocess.Popen(
            [*cmd, "events", "--follow", "--json"], stdout=subprocess.PIPE, text=True, cwd=REPO
        )
        self.lines: list[dict[str, Any]] = []
        self.changed = threading.Condition()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self.changed:
                self.lines.append(json.loads(line))
                self.changed.notify_all()

    def wait_for(self, kind: str, timeout: float = 10.0) -> bool:
        with self.changed:
            return self.changed.wait_for(
                lambda: any(e["kind"] == kind for e in self.lines), timeout
            )

    def stop(self) -> list[dict[str, Any]]:
        stop_process(self.proc)
        self.thread.join(5.0)
        return list(self.lines)


def stored_until_paused(r: Rider, timeout: float = 20.0) -> list[Event]:
    """The machine's events, followed until the state change to PAUSED is among them: the
    history writes a moment after the status it follows is published (run 57, under load,
    read it as the status said PAUSED and found no `rider_lost` yet)."""
    deadline = time.monotonic() + timeout
    events: list[Event] = []
    for event in r.follow_events(EventQuery(since=1), timeout=1.0):
        if event is not None:
            events.append(event)
            if event.kind == "state" and event.details.new is S.PAUSED:  # type: ignore[union-attr]
                return events
        assert time.monotonic() < deadline, f"no state change to PAUSED stored: {events}"
    raise AssertionError("the events' follow ended")


def test_a_lost_rider_is_recorded_with_what_the_policy_did(tmp_path: Path) -> None:
    daemon = start_daemon(tmp_path, extra=fast_args(tmp_path))
    try:
        with daemon.rider() as supervising:  # names itself: it controls the motion
            reply = supervising.calibrate_tilt()
            assert reply.state is S.CALIBRATING
            rider_id = supervising.rider_id
        # Its session closed mid-motion: the machine pauses (rider_loss.policy = pause).
        with daemon.rider(supervise=False) as r:
            r.wait_for({S.PAUSED}, 10.0)
            events = stored_until_paused(r)
    finally:
        daemon.stop()
    kinds = [e.kind for e in events]
    at = kinds.index("rider_lost")
    lost = events[at].details
    assert lost.rider == rider_id and lost.acted and lost.policy == "pause"  # type: ignore[union-attr]
    assert lost.mid_motion is True  # type: ignore[union-attr]
    state = events[at + 1].details
    assert state.kind == "state" and (state.old, state.new) == (S.CALIBRATING, S.PAUSED)  # type: ignore[union-attr]
    assert state.reason == "Rider lost"  # type: ignore[union-attr]


def heard(samples: list[zenoh.Sample]) -> dict[int, Event]:
    """The events among `samples`, by the seq in their key."""
    return {
        int(str(s.key_expr).rsplit("/", 1)[1]): decode(Event, s.payload.to_bytes(), Format.MSGPACK)
        for s in list(samples)
        if "/events/" in str(s.key_expr)
    }


def test_a_subscriber_that_comes_later_gets_every_event_from_then_on(tmp_path: Path) -> None:
    """The daemon makes no event publication while no subscriber matches `events/*` (Zenoh's
    matching status): a storage-like subscriber on `machine/**` and a narrow one on the events,
    each declared after commands nobody heard, get every later event once, as stored."""
    daemon = start_daemon(tmp_path)
    conf = zenoh.Config.from_file(str(daemon.zenoh_config))
    conf.insert_json5("connect/endpoints", json.dumps([daemon.endpoint]))
    try:
        with daemon.rider(supervise=False) as r, zenoh.open(conf) as session:
            for _ in range(5):
                r.check_home()  # nobody follows: stored, not published
            unheard = r.events(last=1)[-1].seq  # a read writes what is queued first
            for key in ("machine/**", f"machine/{daemon.machine_id}/events/*"):
                got: list[zenoh.Sample] = []
                sub = session.declare_subscriber(key, got.append)
                deadline = time.monotonic() + 10.0

                try:
                    while not heard(got):  # until the daemon has seen the subscription
                        r.check_home()
                        assert time.monotonic() < deadline, f"{key}: no event published"
                        time.sleep(0.02)
                    for _ in range(5):
                        r.check_home()
                    last = r.events(last=1)[-1].seq
                    while last not in heard(got):
                        assert time.monotonic() < deadline, f"{key}: events went missing"
                        time.sleep(0.02)
                finally:
                    sub.undeclare()
                events = heard(got)
                first = min(events)
                assert len([s for s in got if "/events/" in str(s.key_expr)]) == len(events)
                stored = [e for e in r.events(since=first) if e.seq <= last]
                assert [events[e.seq] for e in stored] == stored  # every one, as stored
                assert len(stored) >= 5 and first > unheard
    finally:
        daemon.stop()
