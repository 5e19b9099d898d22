"""How a Rider's departure reads (the `rider_lost` event, in `rider events` and the UI).

A Rider that leaves a machine at rest (`rider start --wait` ends its session after DONE) is
routine; one lost while its motion runs, is paused or held by the E-stop is an incident.
"""

from __future__ import annotations


def departure_text(rider: str, policy: str, acted: bool, mid_motion: bool) -> str:
    """One line: left at rest, or lost mid-motion and what the rider-loss policy did."""
    if not mid_motion:
        return f"rider {rider} left at rest (nothing moving: policy {policy} not needed)"
    if acted:
        return f"rider {rider} lost mid-motion: policy {policy} applied"
    later = "the motion goes on" if policy == "ignore" else "its grace period runs"
    return f"rider {rider} lost mid-motion: policy {policy}, {later}"
