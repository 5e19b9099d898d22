"""One session config for both sides: what the daemon and a Rider each get from the shared
zenoh.json5 (or none), their endpoints and their secrets."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ride_machine.common.credentials import MACHINE, RIDER, CredentialError, env_name
from ride_machine.common.zenoh_session import (
    BLOCK_WAIT_SETTING,
    BLOCK_WAIT_US,
    LOCAL_ENDPOINT,
    MACHINE_SIDE,
    MAX_MESSAGE_BYTES,
    MAX_MESSAGE_SETTING,
    RIDER_SIDE,
    file_config,
    zenoh_config,
)
from ride_machine.schema.codec import MAX_REPLY_BYTES
from tests.procs import free_port

REPO = Path(__file__).resolve().parents[2]
SHIPPED = ["zenoh.json5", "zenoh/acl.json5", "zenoh/tls.json5", "docker/rider-client.json5"]

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


def test_every_config_bounds_the_messages_it_reassembles(shared: Path, tmp_path: Path) -> None:
    """Zenoh reassembles fragments into messages of up to 1 GiB by default, for any peer."""
    assert MAX_MESSAGE_BYTES > MAX_REPLY_BYTES  # the largest reply a Rider reads fits
    for side in (MACHINE_SIDE, RIDER_SIDE):
        assert get(zenoh_config(side, None, listen=[]), MAX_MESSAGE_SETTING) == MAX_MESSAGE_BYTES
        assert get(zenoh_config(side, shared, listen=[]), MAX_MESSAGE_SETTING) == MAX_MESSAGE_BYTES
    for name in SHIPPED:  # written in each, for zenohd and other tools that read them too
        shipped = zenoh.Config.from_file(str(REPO / name))
        assert get(shipped, MAX_MESSAGE_SETTING) == MAX_MESSAGE_BYTES, name
    own = tmp_path / "own.json5"
    own.write_text("{transport: {link: {rx: {max_message_size: 4194304}}}}")
    assert get(file_config(own), MAX_MESSAGE_SETTING) == 4194304  # a file's own choice holds


@pytest.mark.hazard("H30")
def test_every_config_cuts_a_peer_that_stops_reading_within_a_quarter_second(
    shared: Path, tmp_path: Path
) -> None:
    """Zenoh waits 5 s for room toward such a peer, holding the sender's thread meanwhile
    (tests/integration/test_hostile_reader.py)."""
    assert get(zenoh.Config(), BLOCK_WAIT_SETTING) == 5_000_000  # Zenoh's own, in µs
    for side in (MACHINE_SIDE, RIDER_SIDE):
        assert get(zenoh_config(side, None, listen=[]), BLOCK_WAIT_SETTING) == BLOCK_WAIT_US
        assert get(zenoh_config(side, shared, listen=[]), BLOCK_WAIT_SETTING) == BLOCK_WAIT_US
    for name in SHIPPED:
        shipped = zenoh.Config.from_file(str(REPO / name))
        assert get(shipped, BLOCK_WAIT_SETTING) == BLOCK_WAIT_US, name
    own = tmp_path / "own.json5"
    own.write_text(
        "{transport: {link: {tx: {queue: {congestion_control: {block:"
        " {wait_before_close: 1000000}}}}}}}"
    )
    assert get(file_config(own), BLOCK_WAIT_SETTING) == 1_000_000  # a file's own choice holds


def _size_of_payload(query: zenoh.Query) -> None:
    with query:
        query.reply(query.key_expr, str(len(query.payload or b"")))


@pytest.mark.hazard("H30")
def test_a_message_past_the_bound_is_dropped_and_the_link_stays() -> None:
    """As the bound does between a daemon and a Rider on two hosts: 1 MiB (the largest reply a
    Rider reads; a request refused by its size) passes, 3 MiB is dropped unreassembled. Shared
    memory is off, as between two hosts: on one host Zenoh hands large messages over in the
    sender's own shared memory instead (its pool, 16 MiB, bounds them)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    confs = [
        zenoh_config(MACHINE_SIDE, None, listen=[endpoint]),
        zenoh_config(RIDER_SIDE, None, listen=[], connect=[endpoint]),
    ]
    for conf in confs:
        conf.insert_json5("transport/shared_memory/enabled", "false")
    server, client = (zenoh.open(conf) for conf in confs)
    try:
        queryable = server.declare_queryable("bound/size", _size_of_payload)
        querier = client.declare_querier("bound/size")
        matched = threading.Event()
        listener = querier.declare_matching_listener(
            lambda status: matched.set() if status.matching else None
        )
        assert querier.matching_status or matched.wait(10.0)  # it has heard of the queryable

        def size(payload: bytes, timeout: float) -> list[str]:
            replies = client.get("bound/size", payload=payload, timeout=timeout)
            return [r.ok.payload.to_bytes().decode() for r in replies if r.ok is not None]

        assert size(b"x" * MAX_REPLY_BYTES, 5.0) == [str(MAX_REPLY_BYTES)]
        assert size(b"x" * (MAX_MESSAGE_BYTES + (1 << 20)), 1.0) == []
        assert size(b"x", 5.0) == ["1"]  # the same link, still up
        for entity in (listener, querier, queryable):
            entity.undeclare()
    finally:
        client.close()
        server.close()
