"""One login per operator station (issue 43, reproduction 1; issue 58, point 3), with the
station logins `machine credentials init --stations bay1,bay2` makes and the shipped profile:
`bay1` supervises a ride, `bay2` is the forger.

Under one shared `rider` login a second process held the victim's `rider/<zid>/alive` token and
put its heartbeat: the victim SIGKILLed mid-session, the ride ran on to DONE with
`rider_connected=true`. Each login now declares and puts under `rider/<its login>/…` only (the
profile's `<login>` rule, made per login by the daemon), and the machine watches the victim's
own `rider/bay1/<zid>/…`: whatever `bay2` holds and feeds, the ride pauses.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from ride_machine.common.credentials import MACHINE, RIDER, env_name
from ride_machine.schema.events import EventQuery, RiderEvent
from ride_machine.service.adapters.credentials import (
    DICTIONARY,
    identities,
    init_credentials,
    password_file,
)
from ride_machine.service.bus.stations import expand
from tests.integration import rider_proc
from tests.reliability.support import (
    ACL_PROFILE,
    TLS_PROFILE,
    Identities,
    rider_as,
    secured_machine,
    start_machine,
)
from tests.reliability.test_access_control import forger

pytestmark = pytest.mark.integration

STATIONS = ("bay1", "bay2")
LOSS_BOUND_S = 10.0
"""The victim's heartbeat timeout (1 s in the fast config) plus a loaded host's margin; the
forger lives 60 s, so a ride it kept alive would still be RUNNING."""


@pytest.fixture(scope="module")
def stations(tmp_path_factory: pytest.TempPathFactory) -> tuple[Identities, Path]:
    """`machine credentials init --stations bay1,bay2`'s files and the shipped profile as it is:
    its `<stations>` subject makes every station login a station (issue 58, point 3; the old
    profile named the shared `rider` only, and bay1 and bay2 could do nothing)."""
    directory = tmp_path_factory.mktemp("stations")
    users = identities(STATIONS)
    init_credentials(directory, users)
    files = {u: password_file(directory, u) for u in users}
    return Identities(directory / DICTIONARY, files, files["monitor"]), ACL_PROFILE


@pytest.mark.hazard("H33")
def test_each_station_login_may_declare_and_put_under_its_own_prefix_only() -> None:
    """The profiles' template, as the daemon makes it (both profiles alike)."""
    for path in (ACL_PROFILE, TLS_PROFILE):
        acl = json.loads(zenoh.Config.from_file(str(path)).get_json("access_control"))
        for subject in acl["subjects"]:
            if subject["id"] == "rider":
                subject["usernames"] = list(STATIONS)
        made = expand(acl)
        rules = {r["id"]: r for r in made["rules"]}
        writes: dict[str, set[str]] = {}
        for policy in made["policies"]:
            if policy["id"] == "router":  # the site's routers forward every station's
                assert policy["rules"] == ["site-link"], policy
                continue
            users = {
                u for s in made["subjects"] if s["id"] in policy["subjects"] for u in s["usernames"]
            }
            for rule_id in policy["rules"]:
                rule = rules[rule_id]
                if "ingress" in rule["flows"] and {"put", "liveliness_token"} & set(
                    rule["messages"]
                ):
                    for key in rule["key_exprs"]:
                        if key.startswith("rider/"):
                            for user in users:
                                writes.setdefault(user, set()).add(key)
        assert writes == {s: {f"rider/{s}/*/alive", f"rider/{s}/*/heartbeat"} for s in STATIONS}, (
            path,
            writes,
        )
        assert not any("<login>" in k for r in made["rules"] for k in r["key_exprs"])


@pytest.mark.hazard("H33")
@pytest.mark.parametrize("command", ["run", "supervise"])
def test_a_second_station_can_neither_hold_nor_feed_the_first_stations_deadman(
    tmp_path_factory: pytest.TempPathFactory, stations: tuple[Identities, Path], command: str
) -> None:
    ids, profile = stations
    tmp = tmp_path_factory.mktemp(f"stations-{command}")
    daemon, victim_env = secured_machine(tmp, ids, command, profile, "bay1")
    try:
        with rider_proc.supervising(daemon, victim_env) as (victim, victim_id):
            zid = victim_id.rsplit("/", 1)[-1]
            # The victim's own keys, the schema-1 ones, and bay2's prefix with the victim's id.
            forged = sorted({f"rider/{victim_id}", f"rider/{zid}", f"rider/bay2/{zid}"})
            args = [
                a for k in forged for a in ("--token", f"{k}/alive", "--beat", f"{k}/heartbeat")
            ]
            with (
                forger(daemon, ids.env(RIDER, "bay2"), *args),
                rider_as(daemon, ids.env(RIDER, "bay2"), timeout=5.0) as observer,
            ):
                what = f"bay2 forging bay1's deadman, {command}"
                rider_proc.assert_loss_pauses(victim, observer, LOSS_BOUND_S, what)
                lost = observer.events(EventQuery(kinds=("rider_lost",)))
        assert any(
            isinstance(e.details, RiderEvent) and e.details.rider == victim_id for e in lost
        ), lost
    finally:
        daemon.stop()


@pytest.mark.hazard("H33")
def test_the_shipped_profile_makes_every_station_login_a_station_at_start(
    tmp_path_factory: pytest.TempPathFactory, stations: tuple[Identities, Path]
) -> None:
    """The shipped profile names no station: the daemon makes each login of the dictionary that
    no other subject names a station as it starts, and says which (issue 58, point 3)."""
    ids, _ = stations
    daemon = start_machine(
        tmp_path_factory.mktemp("stations-shipped"),
        profile=ACL_PROFILE,
        env={env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary)},
        wait=False,
    )
    try:
        assert daemon.has_logged("event=acl_stations logins=bay1,bay2,gateway,ui", 20.0)
        assert "login_without_role" not in daemon.log()
        assert "shared_login" not in daemon.log()
    finally:
        daemon.stop()
