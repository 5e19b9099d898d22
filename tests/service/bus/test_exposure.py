"""Which listen endpoints count as reachable from other hosts, and when a login covers them."""

from __future__ import annotations

import json

import pytest
import zenoh

from ride_machine.service.bus import DEFAULT_LISTEN, zenoh_config
from ride_machine.service.bus.exposure import is_loopback, unauthenticated_exposure


@pytest.mark.parametrize(
    ("endpoint", "local"),
    [
        ("tcp/127.0.0.1:7447", True),
        ("tcp/127.3.2.1:7447", True),
        ("tcp/[::1]:7447", True),
        ("tcp/localhost:7447", True),
        ("tcp/127.0.0.1:7447#iface=lo", True),
        ("unixsock-stream//run/machine.sock", True),
        ("tcp/0.0.0.0:7447", False),
        ("tcp/[::]:7447", False),
        ("tls/10.0.0.5:7447", False),
        ("tcp/machine:7447", False),  # a name may resolve to anything
    ],
)
def test_loopback_endpoints(endpoint: str, local: bool) -> None:
    assert is_loopback(endpoint) is local


def test_the_default_is_loopback_and_not_exposed() -> None:
    conf = zenoh_config(None)
    assert json.loads(conf.get_json("listen/endpoints")) == [DEFAULT_LISTEN]
    assert is_loopback(DEFAULT_LISTEN)
    assert unauthenticated_exposure(conf) == []


def test_the_default_finds_no_peer_by_multicast() -> None:
    """Without a config file the daemon joins only the endpoints it is given, like zenoh.json5:
    Zenoh's own default (multicast scouting) would join any peer on the LAN."""
    assert json.loads(zenoh_config(None).get_json("scouting/multicast/enabled")) is False


def test_wide_listen_is_exposed_unless_a_dictionary_is_set() -> None:
    conf = zenoh_config(None, listen=["tcp/0.0.0.0:7447", "tcp/127.0.0.1:7448"])
    assert unauthenticated_exposure(conf) == ["tcp/0.0.0.0:7447"]
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", '"/run/secrets/zenoh-users"')
    assert unauthenticated_exposure(conf) == []


def test_per_mode_listen_form_uses_the_session_mode() -> None:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", '{router: ["tcp/[::]:7447"], peer: ["tcp/127.0.0.1:0"]}')
    assert unauthenticated_exposure(conf) == []
