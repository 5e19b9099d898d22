"""The one error model on the wire and its codes."""

from __future__ import annotations

from enum import StrEnum

from .base import OpenWireModel


class ErrorCode(StrEnum):
    """Why a request was refused; stable strings that scripts may match on."""

    BAD_PAYLOAD = "BAD_PAYLOAD"
    PAYLOAD_TOO_LARGE = "PAYLOAD_TOO_LARGE"
    UNSUPPORTED_ENCODING = "UNSUPPORTED_ENCODING"
    UNKNOWN_COMMAND = "UNKNOWN_COMMAND"
    BAD_KEY = "BAD_KEY"
    WRONG_STATE = "WRONG_STATE"
    ESTOP_ACTIVE = "ESTOP_ACTIVE"
    NOT_CALIBRATED = "NOT_CALIBRATED"
    NOT_HOME = "NOT_HOME"
    INVALID_SESSION = "INVALID_SESSION"
    DUPLICATE_TRANSACTION = "DUPLICATE_TRANSACTION"
    BUSY = "BUSY"
    UNKNOWN_PARAM = "UNKNOWN_PARAM"
    PARAM_OUT_OF_RANGE = "PARAM_OUT_OF_RANGE"
    PARAM_LOCKED = "PARAM_LOCKED"
    STORAGE_FAILED = "STORAGE_FAILED"
    NOT_AVAILABLE = "NOT_AVAILABLE"
    IN_PROGRESS = "IN_PROGRESS"
    """`done/<transaction_id>` of a motion that has not ended yet (its notice is still due)."""
    UNKNOWN_TRANSACTION = "UNKNOWN_TRANSACTION"
    """`done/<transaction_id>` of no motion this daemon remembers (never one, forgotten, or
    sent before it started)."""
    STALE_REQUEST = "STALE_REQUEST"
    """A command that would move the machine reached it after its sender had stopped waiting
    (`timecode` + `valid_for`, plus the machine's clock margin): it is not acted on."""
    BAD_TIMECODE = "BAD_TIMECODE"
    """A motion command's `timecode` is no time in seconds (milliseconds, a JavaScript
    `Date.now()`), or lies ahead of the machine's clock by more than its clock margin (a clock
    that is wrong, or a request made in advance): it is not acted on."""
    DUPLICATE_ID = "DUPLICATE_ID"
    """Another session holds this machine's id: no command that moves or changes the machine
    is taken until one of the two is alone again."""
    RIDER_UNCONFIRMED = "RIDER_UNCONFIRMED"
    """A motion command named a Rider (`<login>/<zid>`) that did not confirm sending it, asked on
    `rider/<login>/<zid>/confirm`: another sender copied its id, or the Rider does not answer
    there (an older Rider, another client). Nothing moved; send no `rider` field (and no
    attachment naming one) to move unsupervised."""
    SUPERSEDED = "SUPERSEDED"
    """A motion command that was still waiting (for its Rider's confirmation, or for a cycle to
    end) when a Pause or Stop arrived after it: the later stop wins, nothing moved."""
    INTERNAL = "INTERNAL"


class Error(OpenWireModel):
    """What was wrong and where: `path` is a JSON pointer into the request ("" = whole request)."""

    code: ErrorCode
    message: str
    path: str = ""
