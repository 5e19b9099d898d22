"""The daemon's exceptions, and the one place they map to wire error codes."""

from __future__ import annotations

from ride_machine.schema.errors import Error, ErrorCode


class MachineError(Exception):
    """Base of every exception the daemon raises on purpose."""

    code = ErrorCode.INTERNAL
    error_reply = False
    """True: answered as a Zenoh error reply rather than a `Reply` sample (one class only)."""

    def __init__(self, message: str, path: str = "") -> None:
        super().__init__(message)
        self.message = message
        self.path = path

    def to_error(self) -> Error:
        return Error(code=self.code, message=self.message, path=self.path)


class Internal(MachineError):
    """An exception no handler expected (a bug): refused as such, its traceback logged."""

    code = ErrorCode.INTERNAL


class Rejected(MachineError):
    """A refusal that arrives as a wire `Error` already: from the codec (a payload it cannot
    read: `BAD_PAYLOAD`, `PAYLOAD_TOO_LARGE`, `UNSUPPORTED_ENCODING`) or the scan loop's inbox."""

    def __init__(self, error: Error) -> None:
        super().__init__(error.message, error.path)
        self.code = error.code


class BadRequest(MachineError):
    """A request that is well-formed but says nothing to do, or contradicts itself."""

    code = ErrorCode.BAD_PAYLOAD


class WrongState(MachineError):
    code = ErrorCode.WRONG_STATE


class EstopActive(MachineError):
    code = ErrorCode.ESTOP_ACTIVE


class NotCalibrated(MachineError):
    code = ErrorCode.NOT_CALIBRATED


class NotHome(MachineError):
    code = ErrorCode.NOT_HOME


class InvalidSession(MachineError):
    code = ErrorCode.INVALID_SESSION


class DuplicateTransaction(MachineError):
    code = ErrorCode.DUPLICATE_TRANSACTION


class PayloadTooLarge(MachineError):
    code = ErrorCode.PAYLOAD_TOO_LARGE


class UnknownCommand(MachineError):
    """A key under `cmd/` (or `sim/`) that names nothing this machine knows."""

    code = ErrorCode.UNKNOWN_COMMAND


class BadKey(MachineError):
    """A key that may not be used that way (a wildcard on a key that acts, a reset as a
    parameter)."""

    code = ErrorCode.BAD_KEY


class WildcardCommand(BadKey):
    """A wildcard in a command key: refused as a Zenoh error reply (docs/zenoh-cli.md), so a
    caller that reached many machines sees each refusal as an error."""

    error_reply = True


class StaleRequest(MachineError):
    code = ErrorCode.STALE_REQUEST


class BadTimecode(MachineError):
    """A motion command's `timecode` that is not seconds, or is ahead of the machine's clock."""

    code = ErrorCode.BAD_TIMECODE


class OutdatedRider(MachineError):
    """A motion command naming a Rider by the schema-1 id (no login): its deadman is unseen."""

    code = ErrorCode.BAD_PAYLOAD


class RiderUnconfirmed(MachineError):
    """A motion command whose named Rider did not confirm sending it (service/bus/confirm.py)."""

    code = ErrorCode.RIDER_UNCONFIRMED


class Superseded(MachineError):
    """A motion command overtaken by a Pause or Stop that arrived after it."""

    code = ErrorCode.SUPERSEDED


class Busy(MachineError):
    code = ErrorCode.BUSY


class NotAvailable(MachineError):
    code = ErrorCode.NOT_AVAILABLE


class InProgress(MachineError):
    code = ErrorCode.IN_PROGRESS


class UnknownTransaction(MachineError):
    code = ErrorCode.UNKNOWN_TRANSACTION


class UnknownParam(MachineError):
    code = ErrorCode.UNKNOWN_PARAM


class ParamOutOfRange(MachineError):
    code = ErrorCode.PARAM_OUT_OF_RANGE


class ParamWrongType(MachineError):
    """A parameter write whose value has the wrong type (or is missing)."""

    code = ErrorCode.BAD_PAYLOAD


class ParamLocked(MachineError):
    code = ErrorCode.PARAM_LOCKED


class StorageFailed(MachineError):
    code = ErrorCode.STORAGE_FAILED


class DuplicateId(MachineError):
    code = ErrorCode.DUPLICATE_ID
