"""`HostPolicy`: the names `rider ui` answers to and the origins it takes commands from."""

from __future__ import annotations

import socket

import pytest

from ride_machine.rider.ui.app import build_parser
from ride_machine.rider.ui.hosts import BadHostRule, HostPolicy, HostRule, parse_rule


@pytest.mark.hazard("H49")
def test_a_loopback_ui_answers_to_its_address_and_localhost_on_its_port_only() -> None:
    policy = HostPolicy.serving("127.0.0.1", 8080)
    for host in ("127.0.0.1:8080", "localhost:8080", "LOCALHOST:8080"):
        assert policy.host_ok(host), host
    for host in (
        "rebind.test:8080",  # DNS rebinding: the attacker's name, our address
        "127.0.0.1:8081",
        "localhost",  # port 80
        "localhost.:8080",
        "user@localhost:8080",
        "localhost:8080/x",
        "localhost:99999",
        "",
        None,
    ):
        assert not policy.host_ok(host), host
    assert str(policy) == "127.0.0.1:8080, localhost:8080"


@pytest.mark.hazard("H50")
def test_origins_must_be_one_of_its_names_and_never_null() -> None:
    policy = HostPolicy.serving("127.0.0.1", 8080)
    assert policy.origin_ok(None)  # not a browser (curl, a script): the Host check holds
    assert policy.origin_ok("http://127.0.0.1:8080")
    assert policy.origin_ok("http://localhost:8080")
    for origin in (
        "null",
        "http://rebind.test:8080",
        "http://localhost:3000",  # another local web app
        "https://127.0.0.1:8080/",
        "file://",
        "data:text/html,x",
        "http://127.0.0.1",
    ):
        assert not policy.origin_ok(origin), origin


def test_an_ipv6_loopback_ui_answers_to_its_bracketed_address() -> None:
    policy = HostPolicy.serving("::1", 9000)
    assert policy.host_ok("[::1]:9000")
    assert policy.host_ok("localhost:9000")
    assert policy.origin_ok("http://[::1]:9000")
    assert not policy.host_ok("[::2]:9000")
    assert str(policy) == "[::1]:9000, localhost:9000"


def test_a_wildcard_bind_answers_to_any_address_and_its_own_names_on_any_port() -> None:
    """Compose publishes 127.0.0.1:18080 → 8080: the port the browser used is not ours."""
    policy = HostPolicy.serving("0.0.0.0", 8080)
    for host in ("127.0.0.1:18080", "10.1.2.3:8080", "[fd00::5]:8080", "localhost:1"):
        assert policy.host_ok(host), host
    assert policy.host_ok(f"{socket.gethostname()}:8080")
    assert not policy.host_ok("rebind.test:8080")
    assert policy.origin_ok("http://192.168.1.20:8080")
    assert not policy.origin_ok("http://rebind.test:8080")


def test_allowed_hosts_add_a_reverse_proxy_name_on_any_port_or_one() -> None:
    policy = HostPolicy.serving(
        "127.0.0.1", 8080, [parse_rule("hmi.plant.example"), parse_rule("Ops:8443")]
    )
    assert policy.host_ok("hmi.plant.example")
    assert policy.host_ok("hmi.plant.example:443", default_port=443)
    assert policy.origin_ok("https://hmi.plant.example")
    assert policy.host_ok("ops:8443")
    assert not policy.host_ok("ops:8444")
    assert "hmi.plant.example, ops:8443" in str(policy)


@pytest.mark.parametrize(
    "text", ["", "http://hmi", "hmi/x", "hmi:port", "user@hmi", " hmi", "hmi:70000"]
)
def test_a_bad_allowed_host_is_refused_with_the_reason(text: str) -> None:
    with pytest.raises(BadHostRule, match=r"host name|port|Port"):
        parse_rule(text)


def test_allowed_host_is_a_repeatable_option() -> None:
    args = build_parser().parse_args(["--allowed-host", "a.example", "--allowed-host", "b:1"])
    assert args.allowed_host == [HostRule("a.example"), HostRule("b", 1)]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--allowed-host", "http://a.example/"])
