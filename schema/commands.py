"""Commands, their request payloads (with sessions) and the `Reply` envelope."""

from __future__ import annotations

import math
from enum import StrEnum
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, FiniteFloat, StringConstraints, field_validator

from ride_machine.schema import SCHEMA_VERSION

from .base import OpenWireModel, WireModel
from .errors import Error
from .status import MOTION_STATES, MachineState


class Command(StrEnum):
    """Every command the machine takes; `key` is its suffix under `machine/<id>/cmd/`."""

    CALIBRATE_TILT = "CalibrateTilt"
    CALIBRATE_ROTATE = "CalibrateRotate"
    HOME = "Home"
    START = "Start"
    PAUSE = "Pause"
    RESUME = "Resume"
    STOP = "Stop"
    CHECK_CALIBRATION = "CheckCalibration"
    CHECK_HOME = "CheckHome"

    @property
    def key(self) -> str:
        return _KEYS[self]

    @classmethod
    def from_key(cls, key: str) -> Command | None:
        return _BY_KEY.get(key)


_KEYS: dict[Command, str] = {
    Command.CALIBRATE_TILT: "calibrate/tilt",
    Command.CALIBRATE_ROTATE: "calibrate/rotate",
    Command.HOME: "home",
    Command.START: "start",
    Command.PAUSE: "pause",
    Command.RESUME: "resume",
    Command.STOP: "stop",
    Command.CHECK_CALIBRATION: "check/calibration",
    Command.CHECK_HOME: "check/home",
}
_BY_KEY = {v: k for k, v in _KEYS.items()}


_S = MachineState
REST_STATES = frozenset({_S.IDLE, _S.DONE, _S.WARNING_NEEDS_CALIBRATION, _S.WARNING_NOT_HOME})
"""States with no motion and no fault: a new motion command may begin."""

READ_ONLY_COMMANDS = frozenset({Command.CHECK_CALIBRATION, Command.CHECK_HOME})
"""Commands that only read: answered in every state, even with the E-stop active."""

ALLOWED_STATES: dict[Command, frozenset[MachineState]] = {
    Command.CALIBRATE_TILT: REST_STATES | {_S.FAULT_HW},
    Command.CALIBRATE_ROTATE: REST_STATES | {_S.FAULT_HW},
    Command.HOME: REST_STATES | {_S.FAULT_HW, _S.FAULT_ESTOP},
    Command.START: REST_STATES,
    Command.PAUSE: MOTION_STATES,
    Command.RESUME: frozenset({_S.PAUSED, _S.FAULT_ESTOP}),
    Command.STOP: frozenset(_S),
    Command.CHECK_CALIBRATION: frozenset(_S),
    Command.CHECK_HOME: frozenset(_S),
}
"""The states in which the machine accepts each command while the E-stop is released."""


class Direction(StrEnum):
    """Rotation sense seen from above the ride."""

    CW = "cw"
    CCW = "ccw"


_CHUNK = r"[A-Za-z0-9._:+\-][A-Za-z0-9._:@+\-]*"


def _not_a_number(value: object) -> object:
    """Seed 000's transaction ids are numbers; here they are strings, and a number is refused
    with the reason (docs/seeds.md)."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        raise ValueError(
            f"a transaction id is a string, not the number {value!r}: the machine answers a"
            " repeated id from its memory without acting, and numbers from two senders (or one"
            " that restarted) collide; send a string of your own, e.g."
            f' "{value}-bay1-{"<start time>"}"'
        )
    return value


TransactionId = Annotated[
    str,
    StringConstraints(min_length=1, max_length=64, pattern=rf"^{_CHUNK}(?:/{_CHUNK})*$"),
    BeforeValidator(_not_a_number),
]
"""Letters, digits and `._:@+-`, in `/`-separated parts: it names a Zenoh key
(`machine/<id>/done/<transaction_id>`), so no empty part and no part starting with `@`. Not a
number (`_not_a_number`)."""


class TiltStep(WireModel):
    """Tilt the seat to an absolute angle."""

    kind: Literal["tilt"] = "tilt"
    degrees: float

    @field_validator("degrees")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("degrees must be a finite number")
        return v


class RotateStep(WireModel):
    """Rotate whole revolutions, each ending on the home switch."""

    kind: Literal["rotate"] = "rotate"
    direction: Direction = Field(default=Direction.CW, strict=False)
    revolutions: int = Field(default=1, ge=1, le=1000)


Step = Annotated[TiltStep | RotateStep, Field(discriminator="kind")]


class Session(WireModel):
    """A ride program: a named list of steps, run in order."""

    name: str = Field(default="default", min_length=1, max_length=64)
    steps: list[Step] = Field(min_length=1, max_length=100)

    @field_validator("name")
    @classmethod
    def _printable(cls, name: str) -> str:
        # It is shown on terminals, in the UI and in logs: a newline, ESC, NUL or a bidi
        # override would let a session name print a fake line or hide what follows it.
        if not name.isprintable():
            bad = next(c for c in name if not c.isprintable())
            raise ValueError(f"must be printable text; {bad!r} (U+{ord(bad):04X}) is not")
        return name


DEFAULT_SESSION = Session(
    name="default",
    steps=[TiltStep(degrees=45.0), RotateStep(direction=Direction.CW, revolutions=3)],
)


VALID_FOR_MAX_S = 3600
"""The longest `CommandRequest.valid_for` a request may state (an hour)."""


class CommandRequest(WireModel):
    """The envelope of every command: an id that makes a retry safe, and the sender's time.

    `rider` names the sending Rider (its Rider id); the machine watches the Rider that started
    motion and applies the rider-loss policy when it disappears.
    """

    transaction_id: TransactionId
    timecode: FiniteFloat | None = None
    """The sender's clock when it sent the request, in seconds since the Unix epoch (UTC, as
    `time.time()`; a JavaScript Rider sends `Date.now() / 1000`). Seed 000 used integer
    milliseconds; here seconds, as every time on this wire, and a motion command whose timecode
    can only be milliseconds (above 1e11), or lies ahead of the machine's clock by more than
    `bus.clock_margin_s`, is refused `BAD_TIMECODE`. NaN or an infinity is no time: refused
    `BAD_PAYLOAD` (a NaN passed both age checks and started a ride). Echoed in the reply as
    `request_timecode` and written to the daemon's log with the command."""
    rider: TransactionId | None = None
    """The supervising Rider, `<login>/<zid>` (schema/rider.py): the machine watches its
    heartbeat on `rider/<login>/<zid>/heartbeat` while the motion it sent runs. None: nobody
    supervises it (a one-shot command)."""
    valid_for: FiniteFloat | None = Field(default=None, gt=0, le=VALID_FOR_MAX_S)
    """Seconds after `timecode` that the sender still waits for the answer (the Rider sends the
    end of this call's wait: timeout × tries, counted from `timecode`). A command that would
    move the machine and reaches it later than that (a frozen or unreachable daemon that
    resumes) is refused `STALE_REQUEST`, so nothing moves on a command its operator was told
    had timed out. Without `timecode` and `valid_for` (e.g. a hand-written zenoh CLI request)
    no age is checked."""


class StartRequest(CommandRequest):
    """`Start`, optionally with a session (the default session otherwise)."""

    session: Session | None = None


REQUEST_MODELS: dict[Command, type[CommandRequest]] = {c: CommandRequest for c in Command}
REQUEST_MODELS[Command.START] = StartRequest


class ReplyCode(StrEnum):
    """What a successful command did; failures carry `RESP_ERROR` and an `Error`."""

    RESP_START_ACCEPTED = "RESP_START_ACCEPTED"
    RESP_HOME_ACCEPTED = "RESP_HOME_ACCEPTED"
    RESP_CALIBRATION_ACCEPTED = "RESP_CALIBRATION_ACCEPTED"
    RESP_PAUSED = "RESP_PAUSED"
    RESP_RESUMED = "RESP_RESUMED"
    RESP_DONE = "RESP_DONE"
    RESP_CHECK = "RESP_CHECK"
    RESP_ERROR = "RESP_ERROR"


class CheckResult(OpenWireModel):
    """Outcome of CheckCalibration / CheckHome, per axis."""

    ok: bool
    tilt: bool
    rotate: bool


class Reply(OpenWireModel):
    """The one reply every command gets: success or a clear error, and the state afterwards."""

    schema_version: int = SCHEMA_VERSION
    transaction_id: str | None
    command: str | None
    timecode: float
    """The machine's clock when it answered (seconds since the Unix epoch)."""
    request_timecode: float | None = None
    """The request's `timecode`, echoed (None if it carried none)."""
    success: bool
    code: ReplyCode
    state: MachineState | None = None
    result: CheckResult | None = None
    error: Error | None = None
    error_message: str = ""

    @classmethod
    def failure(
        cls,
        error: Error,
        *,
        transaction_id: str | None,
        command: str | None,
        timecode: float,
        state: MachineState | None = None,
        request_timecode: float | None = None,
    ) -> Reply:
        return cls(
            transaction_id=transaction_id,
            command=command,
            timecode=timecode,
            request_timecode=request_timecode,
            success=False,
            code=ReplyCode.RESP_ERROR,
            state=state,
            error=error,
            error_message=error.message,
        )


def transaction_id_of(raw: Any) -> str | None:
    """Best-effort id from an undecodable request, so even its error reply can be matched."""
    if isinstance(raw, dict):
        tid = raw.get("transaction_id")
        if isinstance(tid, str) and 0 < len(tid) <= 64:
            return tid
    return None
