"""What a motion command must carry to be taken: a timecode in seconds that is neither from the
future nor past its sender's wait (`admit`, in the state machine), and a Rider id whose deadman
this machine can watch (`watchable`, at the bus: the key space is the bus's business).

Pure checks (time comes in); each refusal is a `MachineError` whose message says what to send.
"""

from __future__ import annotations

from ride_machine.schema.commands import Command, CommandRequest
from ride_machine.schema.rider import is_rider_id
from ride_machine.service.errors import BadTimecode, OutdatedRider, StaleRequest

SECONDS_MAX = 1e11
"""A `timecode` above this (the year 5138 in seconds) can only be milliseconds or finer: a
JavaScript Rider's `Date.now()` is 1.7e12. Seconds are the one unit on this wire."""


def admit(command: Command, request: CommandRequest, stamp: float, margin: float) -> None:
    """Refuse `request` (a motion `command` reaching the machine at wall time `stamp`) when its
    timecode cannot be read as seconds, lies ahead of this clock by more than `margin`, or its
    sender stopped waiting."""
    _sent_in_seconds(command, request, stamp, margin)
    _fresh(command, request, stamp, margin)


def _sent_in_seconds(
    command: Command, request: CommandRequest, stamp: float, margin: float
) -> None:
    sent = request.timecode
    if sent is None:
        return
    if sent > SECONDS_MAX:
        raise BadTimecode(
            f"{command.value} refused: timecode {sent:.0f} is no time in seconds (it can only"
            " be milliseconds, e.g. a JavaScript Date.now()); send seconds since the Unix epoch"
            " (Date.now() / 1000); nothing moved",
            path="/timecode",
        )
    ahead = sent - stamp
    if ahead > margin:
        raise BadTimecode(
            f"{command.value} refused: timecode {sent:.3f} is {ahead:.1f} s ahead of this"
            f" machine's clock (more than bus.clock_margin_s = {margin:g} s): the sender's"
            " clock is ahead, or the request was made in advance; set the clock (NTP) and send"
            " it again; nothing moved",
            path="/timecode",
        )


def _fresh(command: Command, request: CommandRequest, stamp: float, margin: float) -> None:
    """Refuse a motion command that arrives after its sender stopped waiting for it."""
    if request.timecode is None or request.valid_for is None:
        return
    age = stamp - request.timecode
    if age > request.valid_for + margin:
        raise StaleRequest(
            f"{command.value} refused: sent {age:.1f} s ago, and its sender stopped waiting"
            f" after {request.valid_for:g} s (the machine was not answering, or the two"
            f" clocks differ by more than bus.clock_margin_s = {margin:g} s); nothing"
            " moved: send it again"
        )


def watchable(command: Command, request: CommandRequest) -> None:
    """A Rider of schema 1 names itself by its session id alone and beats on `rider/<zid>/…`,
    which this machine no longer watches: its ride would pause at once, or never be watched."""
    rider = request.rider
    if rider is not None and not is_rider_id(rider):
        raise OutdatedRider(
            f"{command.value} refused: rider {rider!r} names no login (schema 1: rider/<zid>/…);"
            " this machine watches a supervising Rider on rider/<login>/<zid>/… (schema 2):"
            " update the Rider, or send no rider field to move unsupervised; nothing moved",
            path="/rider",
        )
