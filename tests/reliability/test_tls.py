"""The TLS profile (zenoh/tls.json5): a whole ride over `tls/` as the `rider` identity.

The CA and the machine certificate are made with openssl for the test; the daemon listens on
`tls/` only, so a Rider that does not trust the CA, or that dials plain TCP, reaches nothing.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.common.credentials import MACHINE, RIDER, env_name
from ride_machine.rider.client import MachineTimeout, Rider
from ride_machine.schema.commands import RotateStep, Session, TiltStep
from ride_machine.schema.status import MachineState
from tests.integration.support import prepare
from tests.procs import Daemon
from tests.reliability.support import (
    RIDER_VARIABLES,
    TLS_PROFILE,
    Identities,
    StatusFeed,
    Tls,
    environ,
    make_identities,
    make_tls,
    rider_as,
    settle,
    start_machine,
)

pytestmark = pytest.mark.integration

RIDE = Session(name="tls-ride", steps=[TiltStep(degrees=20.0), RotateStep(revolutions=2)])


@pytest.fixture(scope="module")
def secrets_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("tls-secrets")


@pytest.fixture(scope="module")
def ids(secrets_dir: Path) -> Identities:
    return make_identities(secrets_dir / "users")


@pytest.fixture(scope="module")
def tls(secrets_dir: Path) -> Tls:
    return make_tls(secrets_dir / "pki")


@pytest.fixture(scope="module")
def rider_env(ids: Identities, tls: Tls) -> dict[str, str]:
    return {**ids.env(RIDER, "rider"), **tls.rider_env()}


@pytest.fixture(scope="module")
def machine(
    tmp_path_factory: pytest.TempPathFactory, ids: Identities, tls: Tls, rider_env: dict[str, str]
) -> Iterator[Daemon]:
    daemon = start_machine(
        tmp_path_factory.mktemp("tls"),
        profile=TLS_PROFILE,
        scheme="tls",
        env={env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary), **tls.machine_env()},
        rider_env=rider_env,
    )
    try:
        yield daemon
    finally:
        daemon.stop()


def test_calibrate_home_and_a_session_to_done_over_tls(
    machine: Daemon, rider_env: dict[str, str]
) -> None:
    assert machine.endpoint.startswith("tls/")
    with rider_as(machine, rider_env, timeout=5.0) as r:
        feed = StatusFeed(r)
        try:
            status = prepare(r)  # calibrated, homed; a refusal a stall spoiled is measured again
            assert status.calibrated.tilt and status.calibrated.rotate
            reply = r.start(RIDE)
            assert reply.state is MachineState.RUNNING
            done = settle(feed, reply)
        finally:
            feed.close()
        assert done.state is MachineState.DONE, done
        world = r.sim("world")
    assert not any(world.relays.values())
    assert world.tilt_deg == pytest.approx(20.0, abs=3.0)


@pytest.mark.hazard("H32")
def test_a_rider_without_the_ca_reaches_nothing(machine: Daemon, ids: Identities) -> None:
    with rider_as(machine, ids.env(RIDER, "rider"), timeout=1.0) as r:
        assert not list(r.session.info.peers_zid())
        with pytest.raises(MachineTimeout):
            r.status()


@pytest.mark.hazard("H32")
def test_plain_tcp_to_the_tls_port_reaches_nothing(
    machine: Daemon, rider_env: dict[str, str]
) -> None:
    plain = machine.endpoint.replace("tls/", "tcp/", 1)
    with rider_as(machine, rider_env, timeout=1.0) as r0:
        assert list(r0.session.info.peers_zid())  # the same identity over TLS: connected
    with environ({**dict.fromkeys(RIDER_VARIABLES), **rider_env}):
        r = Rider("m1", connect=[plain], zenoh_config_path=machine.zenoh_config, timeout=1.0)
    with r:
        assert not list(r.session.info.peers_zid())
        with pytest.raises(MachineTimeout):
            r.status()
