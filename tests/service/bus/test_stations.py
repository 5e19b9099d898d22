"""One login per station (service/bus/stations.py, service/adapters/credentials.py): the
profile's `<login>` rule made per user name, and the logins `credentials init` makes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from ride_machine.service.adapters.credentials import identities
from ride_machine.service.bus.stations import (
    STATIONS,
    StationError,
    expand,
    fill_stations,
    without_role,
)
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


def test_credentials_are_made_per_station_and_the_shared_login_only_when_asked() -> None:
    assert identities() == ("machine", "ui", "gateway", "monitor")
    stations = identities(("bay1", "bay2"))
    assert stations == ("machine", "ui", "gateway", "bay1", "bay2", "monitor")
    assert "rider" not in stations
    assert identities(shared=True) == ("machine", "ui", "gateway", "rider", "monitor")
    for bad in (("a b",), ("machine",), ("bay1", "bay1"), ("x/y",), ("rider",), ("ui",)):
        with pytest.raises(ValueError):
            identities(bad)


def shipped() -> dict[str, object]:
    return json.loads(zenoh.Config.from_file(str(ACL_PROFILE)).get_json("access_control"))  # type: ignore[no-any-return]


def station_logins(block: dict[str, object]) -> list[str]:
    [rider] = [s for s in block["subjects"] if s["id"] == "rider"]  # type: ignore[attr-defined]
    return rider["usernames"]  # type: ignore[no-any-return]


@pytest.mark.hazard("H33")
def test_the_shipped_profile_makes_each_login_of_the_dictionary_a_station(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    users = tmp_path / "zenoh-users"
    users.write_text("".join(f"{u}:pw\n" for u in (*identities(("bay1", "bay2")), "router")))
    assert station_logins(shipped()) == [STATIONS]  # no login named in the shipped file
    filled = fill_stations(shipped(), users)
    assert station_logins(filled) == ["bay1", "bay2", "gateway", "ui"]
    assert set(without_role(filled, users)) <= {"router"}  # a role's login is never a station
    made = expand(filled)
    assert {p["id"] for p in made["policies"]} >= {"rider@bay1", "rider@ui", "rider@gateway"}
    assert "shared_login" not in caplog.text


@pytest.mark.hazard("H33")
def test_the_shared_login_is_a_station_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    users = tmp_path / "zenoh-users"
    users.write_text("".join(f"{u}:pw\n" for u in identities(shared=True)))
    assert "rider" in station_logins(fill_stations(shipped(), users))
    assert "event=shared_login login=rider" in caplog.text


def test_without_a_station_login_the_placeholder_stays_and_matches_nobody(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A subject without user names would match every login: the placeholder is kept."""
    users = tmp_path / "zenoh-users"
    users.write_text("machine:a\nmonitor:b\n")
    block = fill_stations(shipped(), users)
    assert station_logins(block) == [STATIONS]
    assert "event=no_stations" in caplog.text
    assert not any(s["id"].startswith("rider@") for s in expand(block)["subjects"])
    users.write_text(f"{STATIONS}:x\n")
    with pytest.raises(StationError, match="may not be named"):
        fill_stations(shipped(), users)
