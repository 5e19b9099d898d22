"""The default-machine lookup's pure parts (rider/discovery.py): who dialed whom in a node's
summary, which routers are out of sight, and tokens from a snapshot versus live changes."""

from __future__ import annotations

from typing import Any

import pytest
import zenoh

from ride_machine.rider.discovery import (
    Discovery,
    Listing,
    _apply,
    _Change,
    _Neighbour,
    _probe_brokers,
    _probe_hidden,
    _router,
    _sessions,
)

A_SUMMARY: dict[str, Any] = {
    "zid": "aa",
    "locators": ["tcp/10.0.0.5:7447"],
    "sessions": [
        # a dialed the router: a's end is an ephemeral port
        {
            "peer": "rr",
            "whatami": "router",
            "links": [{"src": "tcp/10.0.0.5:51234", "dst": "tcp/10.0.0.1:7447"}],
        },
        # a Rider dialed a: a's end is its listening port
        {
            "peer": "rd",
            "whatami": "peer",
            "links": [{"src": "tcp/10.0.0.5:7447", "dst": "tcp/10.0.0.9:40000"}],
        },
        {"peer": "cc", "whatami": "client", "links": []},
    ],
}


def test_a_summary_says_which_sessions_the_node_dialed_and_where() -> None:
    assert _sessions(A_SUMMARY) == [
        _Neighbour("rr", "router", "tcp/10.0.0.1:7447"),
        _Neighbour("rd", "peer", None),
        _Neighbour("cc", "client", None),
    ]


def test_a_router_behind_a_node_is_asked_where_the_node_dialed_it() -> None:
    asked: list[str] = []

    def probe(endpoint: str) -> Any:
        asked.append(endpoint)
        raise zenoh.ZError("no answer")

    seen = Discovery(settled=True)
    _probe_hidden(_sessions(A_SUMMARY), {"router"}, {"aa", "me"}, seen, "machine", probe)
    assert asked == ["tcp/10.0.0.1:7447"]
    assert not seen.sure
    assert seen.unseen == ["router rr at tcp/10.0.0.1:7447 (did not answer)"]


def test_a_router_this_session_reached_is_not_asked_again() -> None:
    def probe(endpoint: str) -> Any:
        raise AssertionError("asked a router already reached")

    seen = Discovery(settled=True)
    _probe_hidden(_sessions(A_SUMMARY), {"router"}, {"aa", "rr", "me"}, seen, "machine", probe)
    assert seen.sure


def test_a_router_that_dialed_the_node_has_no_known_address_so_the_lookup_is_unsure() -> None:
    summary = {**A_SUMMARY, "sessions": [{**A_SUMMARY["sessions"][0], "links": []}]}
    seen = Discovery(settled=True)
    _probe_hidden(_sessions(summary), {"router"}, {"aa"}, seen, "machine", None)
    assert seen.unseen == ["router rr (it connected to a node this Rider reached)"]
    assert "out of sight: router rr" in seen.describe()


ROUTER_SUMMARY: dict[str, Any] = {
    "zid": "rr",
    "locators": ["tcp/10.0.0.1:7447"],
    "sessions": [
        # daemon a (a peer) dialed the router, and so did this Rider
        {"peer": "aa", "whatami": "peer", "links": [{"src": "tcp/10.0.0.1:7447"}]},
        {"peer": "me", "whatami": "peer", "links": [{"src": "tcp/10.0.0.1:7447"}]},
        {"peer": "cc", "whatami": "client", "links": [{"src": "tcp/10.0.0.1:7447"}]},
    ],
}


def test_a_reached_router_with_a_peer_not_linked_yet_is_asked_as_a_client() -> None:
    """A router passes no peer's token to a peer Rider (zenoh 1.x: peers link to each other):
    a peer Rider that gossip has not linked to `aa` yet asks the router, where it dialed it
    (tests/site/test_default_pick.py asks a real one)."""
    asked: list[str] = []

    def probe(endpoint: str) -> Any:
        asked.append(endpoint)
        raise zenoh.ZError("no answer")

    router = _router("rr", ROUTER_SUMMARY, "tcp/router.example:7447")
    seen = Discovery(links={"rr"}, settled=True)
    _probe_brokers([router], {"rr", "me"}, seen, "machine", probe)
    assert asked == ["tcp/router.example:7447"]
    assert seen.unseen == ["router rr at tcp/router.example:7447 (did not answer)"]
    assert not seen.sure


def test_a_router_that_dialed_this_session_is_asked_where_it_listens() -> None:
    asked: list[str] = []

    def probe(endpoint: str) -> Any:
        asked.append(endpoint)
        raise zenoh.ZError("no answer")

    seen = Discovery(links={"rr"}, settled=True)
    _probe_brokers([_router("rr", ROUTER_SUMMARY, None)], {"rr", "me"}, seen, "machine", probe)
    assert asked == ["tcp/10.0.0.1:7447"]


def test_a_router_whose_peers_are_all_linked_is_not_asked() -> None:
    def probe(endpoint: str) -> Any:
        raise AssertionError("asked a router whose peers this session is linked to")

    seen = Discovery(links={"rr", "aa"}, settled=True)
    _probe_brokers([_router("rr", ROUTER_SUMMARY, None)], {"rr", "aa", "me"}, seen, "m", probe)
    assert seen.sure


@pytest.mark.parametrize(
    ("changes", "alive"),
    [
        ([_Change("b", True, asked=True)], {"b"}),
        # the subscriber saw b go; a snapshot answered before that must not bring it back
        ([_Change("b", True, False), _Change("b", False, False), _Change("b", True, True)], set()),
        # ... but b coming back live does
        ([_Change("b", False, False), _Change("b", True, False)], {"b"}),
    ],
)
def test_a_snapshot_never_revives_a_machine_seen_going(
    changes: list[_Change], alive: set[str]
) -> None:
    got: set[str] = set()
    gone: set[str] = set()
    for change in changes:
        _apply(change, got, gone)
    assert got == alive


def test_a_client_rider_counts_a_peer_behind_a_node_it_reached_as_out_of_sight() -> None:
    """Gossip never links a client to peers: a peer that dialed a reached node (a Rider, or a
    machine linked only to that node) cannot be asked, so the lookup is unsure."""
    seen = Discovery(settled=True)
    _probe_hidden(_sessions(A_SUMMARY), {"router", "peer"}, {"aa", "rr"}, seen, "machine", None)
    assert seen.unseen == ["peer rd (it connected to a node this Rider reached)"]


def test_a_listing_says_why_it_may_be_incomplete() -> None:
    """`Rider.machines()` lists after discovery; when it could not settle, or part of the
    network was out of sight, the listing is marked incomplete and says why (issue 43)."""
    sure = Discovery(alive={"fa", "fb"}, links={"z1"}, settled=True)
    assert sure.unsure() == ""
    late = Discovery(alive={"fa"}, links={"z1"}, unlinked={"z9"}, waited_s=2.0)
    assert late.unsure().startswith("discovery did not settle within 2.0 s")
    assert "peers not reached yet: z9" in late.unsure()
    hidden = Discovery(alive={"fa"}, links={"z1"}, settled=True, unseen=["router r1 at x"])
    assert hidden.unsure().startswith("part of the network is out of sight")
    listing = Listing(["fa"], complete=False, note=hidden.unsure())
    assert listing == ["fa"] and not listing.complete and "router r1" in listing.note
