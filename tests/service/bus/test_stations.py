"""One login per station (service/bus/stations.py, service/adapters/credentials.py): the
profile's `<login>` rule made per user name, and the logins `credentials init` makes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from service.adapters.credentials import identities
from service.bus.stations import StationError, expand, without_role
from tests.reliability.support import ACL_PROFILE


def acl(*riders: str) -> dict[str, object]:
    block = json.loads(zenoh.Config.from_file(str(ACL_PROFILE)).get_json("access_control"))
    for subject in block["subjects"]:
        if subject["id"] == "rider":
            subject["usernames"] = list(riders)
    return block  # type: ignore[no-any-return]


def test_without_a_template_the_block_is_left_as_it_is() -> None:
    block = {"enabled": True, "rules": [{"id": "r", "key_exprs": ["a/b"]}], "policies": []}
    assert expand(block) is block


@pytest.mark.hazard("H33")
def test_a_user_name_that_cannot_name_keys_stops_the_start() -> None:
    with pytest.raises(StationError, match="cannot name keys"):
        expand(acl("bay 1"))


@pytest.mark.hazard("H54")
def test_every_station_gets_a_subject_and_a_policy_of_its_own() -> None:
    made = expand(acl("bay1", "bay2"))
    ids = {s["id"]: s["usernames"] for s in made["subjects"]}
    assert ids["rider@bay1"] == ["bay1"] and ids["rider@bay2"] == ["bay2"]
    own = {p["id"]: p for p in made["policies"]}
    assert own["rider@bay1"]["rules"] == [
        "supervise-in@bay1",
        "confirm-in@bay1",
        "confirm-out@bay1",
    ]
    assert "supervise-in" not in own["rider"]["rules"]  # the common policy lost the template


def test_a_login_in_the_dictionary_and_in_no_subject_is_named(tmp_path: Path) -> None:
    users = tmp_path / "zenoh-users"
    users.write_text("machine:a\nrider:b\nmonitor:c\nbay3:d\n")
    assert without_role(acl("rider"), users) == ["bay3"]


def test_credentials_are_made_per_station_or_for_the_shared_rider() -> None:
    assert identities() == ("machine", "rider", "monitor")
    assert identities(("bay1", "bay2")) == ("machine", "bay1", "bay2", "monitor")
    for bad in (("a b",), ("machine",), ("bay1", "bay1"), ("x/y",)):
        with pytest.raises(ValueError):
            identities(bad)
