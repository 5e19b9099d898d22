"""Access control in Zenoh itself (zenoh/acl.json5): only the `rider` identity commands.

A real daemon runs the ACL profile with a dictionary made for the test; sessions open as the
rider, as the monitor, with a wrong password, as an unknown user and with no credentials at
all. Every command key (and the parameter, sim, config and diagnostics-reset keys) is tried with
a valid request; the machine's state, parameters, simulated world and cycle counters are
compared before and after.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ride_machine.common.credentials import MACHINE, RIDER, env_name
from ride_machine.rider.client import Rider
from ride_machine.schema.calibration import CalibrationSet, TiltCalibrationSet
from ride_machine.schema.codec import Format, decode, encode, pack
from ride_machine.schema.commands import Command, CommandRequest, Reply, StartRequest
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import EventQuery
from ride_machine.schema.params import ParamSet
from ride_machine.schema.sim import SIM_REQUESTS
from ride_machine.schema.status import MachineState
from tests.integration import rider_proc
from tests.integration.support import raw_get
from tests.procs import REPO, Daemon, free_port, rider_cmd, stop_process
from tests.reliability.forger import FORGED_SEQ
from tests.reliability.support import (
    ACL_PROFILE,
    RIDER_VARIABLES,
    TLS_PROFILE,
    Identities,
    StatusFeed,
    environ,
    make_identities,
    rider_as,
    secured_machine,
    start_machine,
)

pytestmark = pytest.mark.integration

DENIED_WAIT_S = 1.5
"""How long a denied query may wait for a reply that must never come."""
PARAM = "tilt.tolerance_deg"

SIM_FAULTS: dict[str, dict[str, Any]] = {
    "estop": {"pressed": True},
    "home": {"axis": "rotate", "stuck": "closed"},
    "tilt_ai": {"frozen": True},
    "stall": {"axis": "tilt"},
    "clear": {},
    "stalls": {"probability": 1.0, "max_s": 0.05},
    "place": {"tilt_deg": 50.0, "rotate_deg": 10.0},
}


SITE_ROUTERS = ["router", "router-certificate"]
"""The subjects of the site's routers (docker/compose.router.yaml): they forward every login's."""


def forbidden_requests() -> list[tuple[str, bytes]]:
    """Every key that changes something, each with a request the machine would accept."""
    out: list[tuple[str, bytes]] = []
    for n, command in enumerate(Command):
        model = StartRequest if command is Command.START else CommandRequest
        out.append((f"cmd/{command.key}", encode(model(transaction_id=f"intruder-{n}"))))
    out.append(
        (f"params/{PARAM}", encode(ParamSet(transaction_id="intruder-p", value=9.0, persist=True)))
    )
    assert set(SIM_FAULTS) == set(SIM_REQUESTS), "a new sim fault needs a forbidden request"
    out += [
        (f"sim/{k}", pack({"transaction_id": f"intruder-{k}", **v})) for k, v in SIM_FAULTS.items()
    ]
    out.append(("config/validate", b""))
    out.append(("diag/reset", b""))
    cal = CalibrationSet(
        transaction_id="intruder-cal",
        tilt=TiltCalibrationSet(offset_counts=1194.0, gain_counts_per_deg=40.0),
    )
    out.append(("calibration/set", encode(cal)))
    return out


READ_KEYS = ("status", "io/**", "axis/**", "diag/cycle", "calibration")


def fire(session: zenoh.Session, base: str, requests: list[tuple[str, bytes]]) -> dict[str, int]:
    """All requests in flight at once; the number of replies (ok or error) each one got."""
    pending = []
    for key, payload in requests:
        kwargs: dict[str, Any] = {"timeout": DENIED_WAIT_S}
        if payload:
            kwargs.update(payload=payload, encoding=Format.MSGPACK.value)
        pending.append((key, session.get(f"{base}/{key}", **kwargs)))
    return {key: sum(1 for _ in replies) for key, replies in pending}


@dataclass(frozen=True)
class Snapshot:
    """What would change if any forbidden request had acted."""

    status: tuple[object, ...]
    world: dict[str, Any]
    params: dict[str, tuple[object, bool]]
    diag_since: float


def snapshot(r: Rider) -> Snapshot:
    st = r.status()
    world = r.sim("world").model_dump(exclude={"time", "clock"})  # both move by themselves
    params = {p.name: (p.value, p.persisted) for p in r.params()}
    return Snapshot(
        (st.state, st.calibrated, st.homed, st.estop, st.fault, st.session),
        world,
        params,
        r.diag().since,  # moves only when the counters are reset
    )


@pytest.fixture(scope="module")
def ids(tmp_path_factory: pytest.TempPathFactory) -> Identities:
    return make_identities(tmp_path_factory.mktemp("secrets"))


@pytest.fixture(scope="module")
def machine(tmp_path_factory: pytest.TempPathFactory, ids: Identities) -> Iterator[Daemon]:
    daemon = start_machine(
        tmp_path_factory.mktemp("acl"),
        profile=ACL_PROFILE,
        env={env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary)},
        rider_env=ids.env(RIDER, "rider"),
    )
    try:
        yield daemon
    finally:
        daemon.stop()


@contextlib.contextmanager
def session_as(daemon: Daemon, env: dict[str, str]) -> Iterator[Rider]:
    with rider_as(daemon, env, timeout=DENIED_WAIT_S) as r:
        yield r


@pytest.mark.hazard("H32")
def test_profiles_share_one_access_control_block() -> None:
    acl = zenoh.Config.from_file(str(ACL_PROFILE)).get_json("access_control")
    tls = zenoh.Config.from_file(str(TLS_PROFILE)).get_json("access_control")
    assert json.loads(acl) == json.loads(tls)
    assert json.loads(acl)["default_permission"] == "deny"
    listen = json.loads(zenoh.Config.from_file(str(TLS_PROFILE)).get_json("listen/endpoints"))
    assert listen and all(e.startswith("tls/") for e in listen)


def test_rider_identity_commands_writes_params_and_reads(machine: Daemon, ids: Identities) -> None:
    with session_as(machine, ids.env(RIDER, "rider")) as r:
        assert r.status().state is MachineState.WARNING_NEEDS_CALIBRATION
        assert r.check_calibration().ok is False  # a command, answered
        assert r.set_param(PARAM, 1.5).value == 1.5
        assert r.reset_param(PARAM).value == r.param(PARAM).default
        assert r.io() and r.axes() is not None and r.diag().cycles > 0
        before_reset = r.diag(reset=True)
        assert r.diag().since >= before_reset.time  # reset after its reply was stamped
        assert r.validate().ok
        assert r.calibration().complete is False
        assert r.sim("world").estop_pressed is False


@pytest.mark.hazard("H21", "H32")
@pytest.mark.parametrize("who", ["monitor", "wrong password", "unknown user", "no credentials"])
def test_unauthorized_sessions_cannot_command_and_the_machine_does_not_act(
    machine: Daemon, ids: Identities, who: str
) -> None:
    env = {
        "monitor": ids.env(RIDER, "monitor"),
        "wrong password": ids.env(RIDER, "rider", ids.wrong_password),
        "unknown user": ids.env(RIDER, "mallory", ids.password_files["rider"]),
        "no credentials": {},
    }[who]
    with session_as(machine, ids.env(RIDER, "rider")) as rider:
        before = snapshot(rider)
        with session_as(machine, env) as intruder:
            replies = fire(intruder.session, intruder.base, forbidden_requests())
            reads = fire(intruder.session, intruder.base, [(k, b"") for k in READ_KEYS])
            peers = list(intruder.session.info.peers_zid())
        after = snapshot(rider)
    assert replies == dict.fromkeys(replies, 0), f"{who} got answers: {replies}"
    assert after == before
    assert before.status[0] is MachineState.WARNING_NEEDS_CALIBRATION
    assert not any(before.world["relays"].values())
    if who == "monitor":
        # Authenticated, and allowed to read: the denial above is the ACL, not a dead link.
        assert peers
        assert all(n >= 1 for n in reads.values()), reads
    else:
        # Refused at the handshake: no session with the machine at all, not even to read.
        assert not peers
        assert reads == dict.fromkeys(reads, 0)


def test_monitor_reads_status_io_axes_diag_and_subscribes(machine: Daemon, ids: Identities) -> None:
    with session_as(machine, ids.env(RIDER, "monitor")) as m:
        assert m.status().machine_id == "m1"
        assert {p.name for p in m.io()} >= {"estop"}
        assert m.diag().cycles > 0
        assert m.calibration().machine_id == "m1"  # the values, read-only
        feed = StatusFeed(m)
        try:
            assert feed.next().machine_id == "m1"  # a heartbeat reaches a monitor
        finally:
            feed.close()
        assert [i.id for i in m.machines(with_status=False)] == ["m1"]


def test_missing_password_file_is_a_clear_error(machine: Daemon, tmp_path: Path) -> None:
    from ride_machine.rider.client import BadCredentials

    env = {env_name(RIDER, "USER"): "rider", env_name(RIDER, "PASSWORD_FILE"): "/nonexistent"}
    with environ(env), pytest.raises(BadCredentials, match="RIDER_ZENOH_PASSWORD_FILE"):
        machine.rider()


# ------------------------------------------------------------------------------- forgeries
FORGER_START_S = 20.0
LOSS_BOUND_S = 5.0
"""The victim's lease (1 s) plus margin for a loaded host: the pause comes, forged token or not."""


@contextlib.contextmanager
def forger(daemon: Daemon, env: dict[str, str], *args: str) -> Iterator[str]:
    """`tests.reliability.forger` as its own process with its own credentials; yields its zid."""
    child_env = {k: v for k, v in os.environ.items() if k not in RIDER_VARIABLES}
    cmd = [sys.executable, "-m", "tests.reliability.forger", "--connect", daemon.endpoint]
    cmd += ["--listen", f"tcp/127.0.0.1:{free_port()}", "--duration", "60", *args]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, text=True, cwd=REPO, env={**child_env, **env}
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], FORGER_START_S)
        line = proc.stdout.readline() if ready else ""
        assert line.startswith("ready "), f"forger did not start (code {proc.poll()}): {line!r}"
        yield line.split()[1]
    finally:
        stop_process(proc)


FORGED_MACHINE = (
    "--token", "machine/m1/alive",
    "--queryable", "machine/m1/cmd/start",
    "--queryable", "machine/m1/status",
    "--put", "machine/m1/status",
)  # fmt: skip


@pytest.mark.hazard("H34")
@pytest.mark.parametrize("who", ["rider", "monitor"])
def test_a_peer_with_valid_credentials_cannot_pose_as_the_machine(
    machine: Daemon, ids: Identities, who: str, tmp_path: Path
) -> None:
    with forger(machine, ids.env(RIDER, who), *FORGED_MACHINE) as forged_zid:
        # A Rider on Zenoh's defaults (gossip on, as `rider` without --zenoh-config): the one
        # most likely to be told about the forger and dial it.
        with environ({**dict.fromkeys(RIDER_VARIABLES), **ids.env(RIDER, "rider")}):
            rider = Rider("m1", connect=[machine.endpoint], timeout=DENIED_WAIT_S)
        with rider as r:
            feed = StatusFeed(r)
            try:
                # Heartbeats every 0.2 s, forged samples every 0.05 s: 5 real ones would come
                # with ~20 fakes if the forger's publication got through.
                samples = [feed.next() for _ in range(5)]
            finally:
                feed.close()
            assert all(s.seq < FORGED_SEQ for s in samples), samples
            start = encode(StartRequest(transaction_id=f"forgery-{who}"))
            replies = raw_get(r, "cmd/start", start, Format.MSGPACK, DENIED_WAIT_S)
            status_repliers = {
                str(rep.replier_id.zid)
                for rep in r.session.get(f"{r.base}/status", timeout=DENIED_WAIT_S)
                if rep.replier_id is not None
            }
            tokens = list(r.session.liveliness().get("machine/*/alive", timeout=DENIED_WAIT_S))
            peers = {str(z) for z in r.session.info.peers_zid()}
    assert forged_zid not in peers, "the forger got a link to the Rider"
    assert len(replies) == 1, [rep.ok for rep in replies]
    reply = decode(Reply, replies[0].ok.payload.to_bytes(), Format.MSGPACK)  # type: ignore[union-attr]
    assert reply.success is False and reply.error is not None
    assert reply.error.code is ErrorCode.NOT_CALIBRATED  # the real machine's answer
    assert forged_zid not in status_repliers and len(status_repliers) == 1
    assert len(tokens) == 1
    assert "forged" not in machine.log()


@pytest.mark.hazard("H34")
@pytest.mark.parametrize("who", ["rider", "monitor"])
def test_rider_watch_sees_no_forged_status(machine: Daemon, ids: Identities, who: str) -> None:
    """The real CLI, on Zenoh's defaults, while a forger publishes on machine/m1/status."""
    env = {k: v for k, v in os.environ.items() if k not in RIDER_VARIABLES}
    env.update(ids.env(RIDER, "rider"))
    cmd = rider_cmd("--connect", machine.endpoint, "--machine", "m1")
    cmd += ["--json", "watch", "--keys", "status", "--for", "2"]
    with forger(machine, ids.env(RIDER, who), *FORGED_MACHINE):
        done = subprocess.run(
            cmd, check=False, capture_output=True, text=True, timeout=60, cwd=REPO, env=env
        )
    assert done.returncode == 0, done.stderr
    seqs = [json.loads(line)["seq"] for line in done.stdout.splitlines()]
    assert len(seqs) >= 3, done.stdout  # heartbeats every 0.2 s came through
    assert FORGED_SEQ not in seqs


@pytest.mark.hazard("H33")
@pytest.mark.parametrize("command", ["run", "supervise"])
def test_a_monitor_cannot_keep_a_killed_rider_alive(
    tmp_path_factory: pytest.TempPathFactory, ids: Identities, command: str
) -> None:
    """Issue 15, point 3: the monitor holds `rider/<victim>/alive`; the victim is SIGKILLed.

    Under `supervise` the Riders' tokens reach the daemon child through the supervisor's
    router as the `machine` identity (which may watch rider/** but never declare there).
    """
    tmp = tmp_path_factory.mktemp("acl-loss")
    daemon, victim_env = secured_machine(tmp, ids, command, ACL_PROFILE, "rider")
    try:
        with (
            rider_proc.supervising(daemon, victim_env) as (victim, victim_id),
            forger(daemon, ids.env(RIDER, "monitor"), "--token", f"rider/{victim_id}/alive"),
            session_as(daemon, ids.env(RIDER, "rider")) as observer,
        ):
            what = f"forged token, {command}"
            rider_proc.assert_loss_pauses(victim, observer, LOSS_BOUND_S, what)
    finally:
        daemon.stop()


def test_monitor_reads_and_follows_the_event_history(machine: Daemon, ids: Identities) -> None:
    with (
        session_as(machine, ids.env(RIDER, "monitor")) as m,
        session_as(machine, ids.env(RIDER, "rider")) as r,
    ):
        assert m.events(last=1)[0].machine_id == "m1"  # the query is allowed
        live = m.follow_events(EventQuery(last=1), timeout=5.0)
        next(live)  # the history's newest event
        r.check_home()  # one `command` event, published on events/<seq>
        event = next(e for e in live if e is None or e.kind == "command")
        assert event is not None and event.details.command == "CheckHome"  # type: ignore[union-attr]
        live.close()


@pytest.mark.hazard("H41")
def test_no_identity_but_the_machine_may_put_or_delete_events() -> None:
    """The ACL itself: events are read-only over the bus for riders and monitors (a router
    with the same profile keeps a site's stored copy read-only too). The site's routers carry
    other machines' events as they carry everything, each login checked where it connects."""
    for profile in (ACL_PROFILE, TLS_PROFILE):
        acl = json.loads(zenoh.Config.from_file(str(profile)).get_json("access_control"))
        rules = {rule["id"]: rule for rule in acl["rules"]}
        for policy in acl["policies"]:
            if policy["subjects"] in (["machine"], SITE_ROUTERS):
                continue
            for rule_id in policy["rules"]:
                rule = rules[rule_id]
                writes = {"put", "delete"} & set(rule["messages"])
                touches = any("events" in k or k.endswith("/**") for k in rule["key_exprs"])
                assert not (writes and "ingress" in rule["flows"] and touches), (profile, rule_id)


@pytest.mark.parametrize(
    ("command", "code"),
    [(["--machine", "m1", "status"], 3), (["status"], 3), (["machines"], 0)],
    ids=["named", "unnamed", "machines"],
)
def test_a_refused_login_says_authentication_refused(
    machine: Daemon, ids: Identities, command: list[str], code: int
) -> None:
    env = {k: v for k, v in os.environ.items() if k not in RIDER_VARIABLES}
    env.update(ids.env(RIDER, "rider", ids.wrong_password))
    args = ["--connect", machine.endpoint, "--zenoh-config", str(machine.zenoh_config)]
    done = subprocess.run(
        rider_cmd(*args, "--timeout", "1", *command),
        check=False, capture_output=True, text=True, timeout=60, cwd=REPO, env=env,
    )  # fmt: skip
    said = done.stderr + done.stdout
    assert done.returncode == code, said
    assert "authentication refused?" in said
    assert "RIDER_ZENOH_PASSWORD_FILE" in said


def test_a_rider_without_a_login_is_not_told_its_login_was_refused(machine: Daemon) -> None:
    """Issue 58, point 6: a session that presents no login was told "authentication refused?
    (check RIDER_ZENOH_USER …)", on an open machine too. It is told what was seen: it logs in
    as nobody, and the machine asks for a login (this one does) or is restarting."""
    env = {k: v for k, v in os.environ.items() if k not in RIDER_VARIABLES}
    args = ["--connect", machine.endpoint, "--zenoh-config", str(machine.zenoh_config)]
    done = subprocess.run(
        rider_cmd(*args, "--timeout", "1", "status"),
        check=False, capture_output=True, text=True, timeout=60, cwd=REPO, env=env,
    )  # fmt: skip
    said = done.stderr + done.stdout
    assert done.returncode == 3, said
    assert "authentication refused?" not in said
    assert "logs in as nobody (no RIDER_ZENOH_USER)" in said


def test_nothing_listening_is_not_called_a_refused_login() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    done = subprocess.run(
        rider_cmd("--connect", endpoint, "--timeout", "1", "status"),
        check=False, capture_output=True, text=True, timeout=60, cwd=REPO,
    )  # fmt: skip
    assert done.returncode == 3, done.stderr
    assert "authentication refused?" not in done.stderr
    assert f"nothing answers at {endpoint}" in done.stderr


@pytest.mark.hazard("H33")
def test_only_the_rider_identity_may_declare_or_put_under_rider() -> None:
    """The ACL itself: rider/** (presence tokens, deadman heartbeats) is written by `rider`
    alone; the monitor and even the machine's own login may only watch it. The site's routers
    carry the stations' (each checked at the router it logs in to: test_site_router.py)."""
    for profile in (ACL_PROFILE, TLS_PROFILE):
        acl = json.loads(zenoh.Config.from_file(str(profile)).get_json("access_control"))
        rules = {rule["id"]: rule for rule in acl["rules"]}
        writers = set()
        for policy in acl["policies"]:
            for rule_id in policy["rules"]:
                rule = rules[rule_id]
                writes = {"put", "delete", "liveliness_token", "declare_queryable"}
                if not (writes & set(rule["messages"]) and "ingress" in rule["flows"]):
                    continue
                if any(k.startswith("rider/") for k in rule["key_exprs"]):
                    writers.update(policy["subjects"])
        assert writers == {"rider", *SITE_ROUTERS}, (profile, writers)
