"""The keys a Rider speaks on (outside `machine/<id>`): its presence and its deadman heartbeat.

A supervising Rider holds `rider/<zid>/alive` (a liveliness token) and puts an empty sample on
`rider/<zid>/heartbeat` every `HEARTBEAT_INTERVAL_S`. The machine judges the Rider that started
a motion by that heartbeat, not by the token: the token lives as long as the Rider's Zenoh lease
(10 s by default), the heartbeat stops the moment the Rider freezes, dies or loses its link.
"""

from __future__ import annotations

HEARTBEAT_INTERVAL_S = 0.1
"""How often a supervising Rider puts its heartbeat; `rider_loss.timeout_s` is checked
against it."""

ALIVE_KEYS = "rider/*/alive"
HEARTBEAT_KEYS = "rider/*/heartbeat"


def alive_key(zid: str) -> str:
    return f"rider/{zid}/alive"


def heartbeat_key(zid: str) -> str:
    return f"rider/{zid}/heartbeat"


def rider_of(key: str) -> str | None:
    """The Rider id in `rider/<zid>/alive|heartbeat`; None for anything else (a Rider's id is
    its session id, hex)."""
    parts = key.split("/")
    if len(parts) != 3 or parts[0] != "rider" or not parts[1].isalnum():
        return None
    return parts[1]
