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
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from rider.client import Rider
from schema.codec import Format, encode, pack
from schema.commands import Command, CommandRequest, StartRequest
from schema.credentials import MACHINE, RIDER, env_name
from schema.params import ParamSet
from schema.sim import SIM_REQUESTS
from schema.status import MachineState
from tests.procs import Daemon
from tests.reliability.support import (
    ACL_PROFILE,
    TLS_PROFILE,
    Identities,
    StatusFeed,
    environ,
    make_identities,
    rider_as,
    start_machine,
)

pytestmark = pytest.mark.integration

DENIED_WAIT_S = 1.5
"""How long a denied query may wait for a reply that must never come."""
PARAM = "rider_loss.grace_s"

SIM_FAULTS: dict[str, dict[str, Any]] = {
    "estop": {"pressed": True},
    "home": {"axis": "rotate", "stuck": "closed"},
    "tilt_ai": {"frozen": True},
    "stall": {"axis": "tilt"},
    "clear": {},
}


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
    return out


READ_KEYS = ("status", "io/**", "axis/**", "diag/cycle")


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
    world = r.sim("world").model_dump(exclude={"time"})
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
        assert r.sim("world").estop_pressed is False


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
        feed = StatusFeed(m)
        try:
            assert feed.next().machine_id == "m1"  # a heartbeat reaches a monitor
        finally:
            feed.close()
        assert [i.id for i in m.machines(with_status=False)] == ["m1"]


def test_missing_password_file_is_a_clear_error(machine: Daemon, tmp_path: Path) -> None:
    from rider.client import BadCredentials

    env = {env_name(RIDER, "USER"): "rider", env_name(RIDER, "PASSWORD_FILE"): "/nonexistent"}
    with environ(env), pytest.raises(BadCredentials, match="RIDER_ZENOH_PASSWORD_FILE"):
        machine.rider()
