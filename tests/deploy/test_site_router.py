"""The site router of docker/compose.router.yaml enforces the machine's logins (issue 57,
reproduction 1: through the router, `monitor` commanded the ride).

The router service runs here as compose runs it (its command and environment read from the
file, container paths made this host's, its published ports loopback ports), twice: router A,
which the machine dials over TLS as compose's machine does, and router B, another host's,
joined to A by its SITE_ROUTER_CONNECT. A Rider reaches the machine through one router (A) or
two (B, then A). The profile is the shipped zenoh/acl.json5, unchanged, for the machine and both
routers; the logins are `machine credentials init --stations bay1,bay2`'s, the router's
certificate and login docker/site-certs.sh's. Through either path: `monitor` reads and is
refused every command, a station's forged deadman does not keep another station's ride alive,
and a Rider without a login (or with a wrong password) gets no session at all.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from ride_machine.common.credentials import MACHINE, RIDER, env_name
from ride_machine.rider.errors import MachineTimeout
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import EventQuery, RiderEvent
from ride_machine.schema.status import MachineState
from ride_machine.service.adapters.credentials import (
    DICTIONARY,
    identities,
    init_credentials,
    password_file,
)
from tests.deploy import spec
from tests.deploy.test_topology import Child
from tests.integration import rider_proc
from tests.integration.support import prepare
from tests.procs import REPO, Daemon, free_port
from tests.reliability.support import ACL_PROFILE, Identities, rider_as, start_machine
from tests.reliability.test_access_control import (
    READ_KEYS,
    fire,
    forbidden_requests,
    forger,
    snapshot,
)
from tests.reliability.test_attribution import forge

pytestmark = pytest.mark.integration

STATIONS = ("bay1", "bay2")
ROUTER_LOGIN = "router"
SITE_CLIENT = REPO / "docker" / "rider-client.json5"
CERTS = REPO / "docker" / "site-certs.sh"
RIDERS_LISTEN = "tcp/0.0.0.0:7447"
SITE_LISTEN = "tls/0.0.0.0:7448"
READY_TIMEOUT_S = 30.0
DENIED_WAIT_S = 2.0
LOSS_BOUND_S = 10.0
"""The victim's heartbeat timeout (1 s in the fast config) plus a loaded host's margin."""


@dataclass
class Router:
    child: Child
    riders: str
    """Where Riders log in (tcp/)."""
    site: str
    """Where the machine and other routers dial it (tls/)."""


@dataclass
class Site:
    ids: Identities
    machine: Daemon
    routers: list[Router]

    def via(self, hops: int) -> Daemon:
        """The machine as a Rider reaches it through `hops` routers (client mode)."""
        router = self.routers[hops - 1]
        return dataclasses.replace(self.machine, endpoint=router.riders, zenoh_config=SITE_CLIENT)

    def logs(self) -> str:
        routers = "\n".join(f"--- router {n}\n{r.child.log()}" for n, r in enumerate(self.routers))
        return f"{routers}\n--- machine\n{self.machine.log()}"


def make_certificate(directory: Path) -> None:
    """The router's certificate and login as the docs make them, after the site's logins, for
    loopback (one for both routers)."""
    done = subprocess.run(
        ["sh", str(CERTS), str(directory), "localhost", "127.0.0.1"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    for name in ("site-ca.crt", "router.crt", "router.key", "router.password"):
        assert (directory / name).stat().st_mode & 0o077 == 0, name
    password = password_file(directory, ROUTER_LOGIN).read_text().strip()
    assert f"{ROUTER_LOGIN}:{password}" in (directory / DICTIONARY).read_text().splitlines()


def start_router(secrets: Path, profile: Path, connect: str = "") -> Router:
    """The router service of docker/compose.router.yaml on loopback ports."""
    svc = spec.service(
        spec.load_compose(spec.ROUTER_OVERRIDE, {"SITE_ROUTER_CONNECT": connect}), "router"
    )
    riders, site = f"tcp/127.0.0.1:{free_port()}", f"tls/127.0.0.1:{free_port()}"
    replace = {"./zenoh/acl.json5": profile, "./secrets/site-ca.crt": secrets / "site-ca.crt"}
    paths = {
        **spec.mount_paths(svc, secrets / "volumes", replace),
        **{target: secrets / Path(target).name for target in secret_targets(svc)},
        "/opt/site-router": REPO / "docker",
    }
    argv = spec.host_argv(spec.command(svc), paths)
    argv = [{RIDERS_LISTEN: riders, SITE_LISTEN: site}.get(a, a) for a in argv]
    env = {k: spec.host_path(v, paths) for k, v in spec.environment(svc).items()}
    child = Child.start("router", argv, {**clean_env(), "PYTHONUNBUFFERED": "1", **env})
    child.wait_line("event=router_ready", READY_TIMEOUT_S)
    return Router(child, riders, site)


def secret_targets(svc: dict[str, object]) -> list[str]:
    return [f"{spec.SECRETS_DIR}/{name}" for name in svc.get("secrets") or []]  # type: ignore[attr-defined]


def clean_env() -> dict[str, str]:
    """This process's environment without anybody's Zenoh login."""
    import os

    return {k: v for k, v in os.environ.items() if "_ZENOH_" not in k}


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    """Machine → router A (the machine dials it) ← router B (dials A): Riders log in to either."""
    secrets = tmp_path_factory.mktemp("site-secrets")
    users = (*identities(STATIONS), ROUTER_LOGIN)
    init_credentials(secrets, users[:-1])
    make_certificate(secrets)  # and the router's login
    files = {u: password_file(secrets, u) for u in users}
    ids = Identities(secrets / DICTIONARY, files, files["monitor"])
    profile = ACL_PROFILE  # as shipped: its <stations> are the dictionary's stations
    routers: list[Router] = []
    machine = None
    try:
        routers.append(start_router(secrets, profile))
        routers.append(start_router(secrets, profile, connect=routers[0].site))
        env = {
            env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary),
            env_name(MACHINE, "TLS_ROOT_CA"): str(secrets / "site-ca.crt"),
            **ids.env(MACHINE, "machine"),
        }
        machine = start_machine(
            tmp_path_factory.mktemp("site-machine"),
            command="supervise",
            profile=profile,
            env=env,
            rider_env=ids.env(RIDER, "bay1"),
            extra=["--connect", routers[0].site],
        )
        yield Site(ids, machine, routers)
    finally:
        if machine is not None:
            machine.stop()
        for router in reversed(routers):
            assert router.child.stop() == 0, router.child.log()


def rider_env(site: Site, user: str, password: Path | None = None) -> dict[str, str]:
    return {**clean_env(), **site.ids.env(RIDER, user, password)}


@pytest.mark.parametrize("hops", [1, 2], ids=["one router", "two routers"])
def test_through_the_routers_a_station_commands_and_reads(site: Site, hops: int) -> None:
    """The other tests' refusals are the ACL's, not a dead path: a station's command, reads
    and status samples go through."""
    with rider_as(site.via(hops), site.ids.env(RIDER, "bay1"), timeout=10.0) as r:
        assert r.status().machine_id == "m1"
        assert r.check_calibration().ok is False  # a command, answered
        assert {p.name for p in r.io()} >= {"estop"}


@pytest.mark.hazard("H32")
@pytest.mark.parametrize("hops", [1, 2], ids=["one router", "two routers"])
@pytest.mark.parametrize("who", ["monitor", "wrong password", "unknown user", "no login"])
def test_through_the_routers_only_a_station_login_commands(site: Site, hops: int, who: str) -> None:
    env = {
        "monitor": site.ids.env(RIDER, "monitor"),
        "wrong password": site.ids.env(RIDER, "bay1", site.ids.wrong_password),
        "unknown user": site.ids.env(RIDER, "mallory", site.ids.password_files["bay1"]),
        "no login": {},
    }[who]
    via = site.via(hops)
    if who != "monitor":
        # A client (the site Rider's mode) refused at the router's handshake cannot even open.
        with pytest.raises(MachineTimeout, match="cannot open"), rider_as(via, env, timeout=2):
            pass
        # A peer opens without a link; it asks anyway.
        via = dataclasses.replace(via, zenoh_config=site.machine.zenoh_config)
    with rider_as(site.via(hops), site.ids.env(RIDER, "bay1"), timeout=10.0) as station:
        before = snapshot(station)
        with rider_as(via, env, timeout=DENIED_WAIT_S) as intruder:
            replies = fire(intruder.session, intruder.base, forbidden_requests())
            reads = fire(intruder.session, intruder.base, [(k, b"") for k in READ_KEYS])
            linked = [*intruder.session.info.routers_zid(), *intruder.session.info.peers_zid()]
        after = snapshot(station)
    assert replies == dict.fromkeys(replies, 0), f"{who} got answers: {replies}\n{site.logs()}"
    assert after == before
    if who == "monitor":
        # Logged in, and it reads through the routers: the denial above is the ACL's.
        assert linked
        assert all(n >= 1 for n in reads.values()), reads
    else:
        assert not linked
        assert reads == dict.fromkeys(reads, 0)


@pytest.mark.hazard("H33")
@pytest.mark.parametrize("forger_hops", [1, 2], ids=["forger at A", "forger at B"])
def test_a_station_cannot_keep_another_stations_ride_alive_through_the_routers(
    site: Site, forger_hops: int
) -> None:
    """bay1 rides supervised through both routers; bay2 holds bay1's token and feeds its
    heartbeat at either router; bay1 is SIGKILLed: the ride pauses, bay1's Rider lost."""
    victim_path, forger_path = site.via(2), site.via(forger_hops)
    with rider_as(site.via(1), site.ids.env(RIDER, "bay1"), timeout=10.0) as r:
        r.stop()  # a ride paused by the other case ends: a fresh one from rest
    with rider_proc.supervising(victim_path, rider_env(site, "bay1")) as (victim, victim_id):
        zid = victim_id.rsplit("/", 1)[-1]
        forged = sorted({f"rider/{victim_id}", f"rider/{zid}", f"rider/bay2/{zid}"})
        args = [a for k in forged for a in ("--token", f"{k}/alive", "--beat", f"{k}/heartbeat")]
        with (
            forger(forger_path, rider_env(site, "bay2"), *args),
            rider_as(site.via(1), site.ids.env(RIDER, "bay2"), timeout=5.0) as observer,
        ):
            what = f"bay2 forging bay1's deadman, {forger_hops} router(s) from the machine"
            paused = rider_proc.assert_loss_pauses(victim, observer, LOSS_BOUND_S, what)
            lost = observer.events(EventQuery(kinds=("rider_lost",)))
    assert paused.state is MachineState.PAUSED
    assert any(isinstance(e.details, RiderEvent) and e.details.rider == victim_id for e in lost), (
        lost
    )


@pytest.mark.hazard("H54")
@pytest.mark.parametrize("hops", [1, 2], ids=["one router", "two routers"])
def test_a_station_naming_anothers_rider_is_not_confirmed_through_the_routers(
    site: Site, hops: int
) -> None:
    """bay2 names bay1's Rider in a Start and answers yes on bay1's confirm key: the machine's
    question crosses the routers to bay1's Rider, which did not send it, and bay2's answer is
    dropped at its router (RIDER_UNCONFIRMED; nothing moves). bay1's own Start is confirmed."""
    with rider_as(site.via(hops), site.ids.env(RIDER, "bay1"), timeout=10.0) as bay1:
        bay1.stop()  # a ride another test left paused ends: prepare from rest
        prepare(bay1)
        forged, _ = forge(site.via(hops), site.ids.env(RIDER, "bay2"), bay1.rider_id)
        assert forged.error is not None and forged.error.code is ErrorCode.RIDER_UNCONFIRMED, (
            f"{forged}\n{site.logs()}"
        )
        assert bay1.status().state is MachineState.IDLE
        own = bay1.start()
        assert own.success, own
        bay1.stop()


@pytest.mark.parametrize(
    ("args", "env", "reason"),
    [
        (["--zenoh-config", str(REPO / "zenoh.json5")], {}, "no access control"),
        (["--connect", "tcp/127.0.0.1:1"], {}, "dials tls/ only"),
        (["--connect", "tls/127.0.0.1:1"], {"TLS_ROOT_CA": None}, "MACHINE_ZENOH_TLS_ROOT_CA"),
        ([], {"DICTIONARY_FILE": None}, "MACHINE_ZENOH_DICTIONARY_FILE"),
        (["--listen", "tls/127.0.0.1:1"], {"TLS_CERTIFICATE": None}, "TLS_CERTIFICATE"),
    ],
    ids=["open profile", "tcp dial", "no CA", "no dictionary", "no certificate"],
)
@pytest.mark.hazard("H32")
def test_the_router_refuses_a_config_that_would_not_enforce_the_profile(
    tmp_path: Path, args: list[str], env: dict[str, None], reason: str
) -> None:
    secrets = tmp_path / "secrets"
    init_credentials(secrets, ("machine", "monitor"))
    make_certificate(secrets)
    full = {
        "DICTIONARY_FILE": secrets / DICTIONARY,
        "USER": ROUTER_LOGIN,
        "PASSWORD_FILE": password_file(secrets, ROUTER_LOGIN),
        "TLS_ROOT_CA": secrets / "site-ca.crt",
        "TLS_CERTIFICATE": secrets / "router.crt",
        "TLS_PRIVATE_KEY": secrets / "router.key",
    }
    variables = {env_name(MACHINE, k): str(v) for k, v in full.items() if k not in env}
    if "--zenoh-config" not in args:
        args = ["--zenoh-config", str(ACL_PROFILE), *args]
    done = subprocess.run(
        [sys.executable, str(REPO / "docker" / "site_router.py"), *args],
        capture_output=True, text=True, timeout=60, cwd=REPO, check=False,
        env={**clean_env(), **variables},
    )  # fmt: skip
    assert done.returncode == 2, done.stdout + done.stderr
    assert reason in done.stderr
