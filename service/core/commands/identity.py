"""Who asked, once proven: the Rider that confirmed a request (service/bus/confirm.py)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Identity:
    """A request's Rider once it confirmed that it sent it, and the person it acted for when it
    names one (the plant gateway's OPC UA user): what the history records as who asked."""

    rider: str
    """`<login>/<zid>`: under the ACL profiles only that login can confirm."""
    operator: str | None = None
    """The person at the Rider, as the Rider names them in its confirmation (schema/rider.py)."""
