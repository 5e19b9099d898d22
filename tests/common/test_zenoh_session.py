"""One session config for both sides: what the daemon and a Rider each get from the shared
zenoh.json5 (or none), their endpoints and their secrets."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ride_machine.common.credentials import MACHINE, RIDER, CredentialError, env_name
from ride_machine.common.zenoh_session import LOCAL_ENDPOINT, MACHINE_SIDE, RIDER_SIDE, zenoh_config

FILE = """{
  mode: "peer",
  listen: { endpoints: ["tcp/127.0.0.1:9001"] },
  connect: { endpoints: ["tcp/127.0.0.1:9002"] },
  scouting: { multicast: { enabled: false } },
}
"""


def get(conf: zenoh.Config, path: str) -> Any:
    return json.loads(conf.get_json(path) or "null")


@pytest.fixture
def shared(tmp_path: Path) -> Path:
    path = tmp_path / "zenoh.json5"
    path.write_text(FILE)
    return path


@pytest.fixture(autouse=True)
def no_secrets(monkeypatch: pytest.MonkeyPatch) -> None:
    for side in (MACHINE, RIDER):
        for item in ("USER", "PASSWORD_FILE", "DICTIONARY_FILE"):
            monkeypatch.delenv(env_name(side, item), raising=False)


def test_without_a_file_the_daemon_listens_on_this_host_with_a_readable_admin_space() -> None:
    conf = zenoh_config(MACHINE_SIDE, None)
    assert get(conf, "mode") == "peer"
    assert get(conf, "listen/endpoints") == [LOCAL_ENDPOINT]
    assert get(conf, "connect/endpoints") == []
    assert get(conf, "scouting/multicast/enabled") is False
    assert get(conf, "adminspace/enabled") is True
    assert get(conf, "adminspace/permissions") == {"read": True, "write": False}


def test_without_a_file_a_rider_connects_to_this_host_and_listens_nowhere() -> None:
    conf = zenoh_config(RIDER_SIDE, None, listen=[])
    assert get(conf, "mode") == "peer"
    assert get(conf, "listen/endpoints") == []
    assert get(conf, "connect/endpoints") == [LOCAL_ENDPOINT]
    assert get(conf, "scouting/multicast/enabled") is False
    assert get(conf, "adminspace/enabled") is False


def test_the_file_holds_unless_endpoints_are_given(shared: Path) -> None:
    daemon = zenoh_config(MACHINE_SIDE, shared)
    assert get(daemon, "listen/endpoints") == ["tcp/127.0.0.1:9001"]
    assert get(daemon, "adminspace/enabled") is False  # Zenoh's default: the file did not ask
    daemon = zenoh_config(MACHINE_SIDE, shared, listen=["tcp/127.0.0.1:9003"], connect=["x/y"])
    assert get(daemon, "listen/endpoints") == ["tcp/127.0.0.1:9003"]
    assert get(daemon, "connect/endpoints") == ["x/y"]
    rider = zenoh_config(RIDER_SIDE, shared, listen=[])
    assert get(rider, "listen/endpoints") == []  # a Rider never takes the daemon's port
    assert get(rider, "connect/endpoints") == ["tcp/127.0.0.1:9002"]  # the file's, not the default
    assert get(rider, "adminspace/enabled") is False  # whatever the file says


def test_each_side_presents_its_own_secrets(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    password = tmp_path / "password"
    password.write_text("s3cret\n")
    monkeypatch.setenv(env_name(RIDER, "USER"), "station-1")
    monkeypatch.setenv(env_name(RIDER, "PASSWORD_FILE"), str(password))
    rider = zenoh_config(RIDER_SIDE, None, listen=[])
    assert get(rider, "transport/auth/usrpwd/user") == "station-1"
    assert get(rider, "transport/auth/usrpwd/password") == "s3cret"
    daemon = zenoh_config(MACHINE_SIDE, None)
    assert get(daemon, "transport/auth/usrpwd/user") is None
    monkeypatch.setenv(env_name(MACHINE, "USER"), "machine")
    with pytest.raises(CredentialError, match=env_name(MACHINE, "PASSWORD_FILE")):
        zenoh_config(MACHINE_SIDE, None)
