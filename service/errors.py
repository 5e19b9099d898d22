"""The daemon's exceptions, and the one place they map to wire error codes."""

from __future__ import annotations

from schema.errors import Error, ErrorCode


class MachineError(Exception):
    """Base of every exception the daemon raises on purpose."""

    code = ErrorCode.INTERNAL

    def __init__(self, message: str, path: str = "") -> None:
        super().__init__(message)
        self.message = message
        self.path = path

    def to_error(self) -> Error:
        return Error(code=self.code, message=self.message, path=self.path)


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


class UnknownParam(MachineError):
    code = ErrorCode.UNKNOWN_PARAM


class ParamOutOfRange(MachineError):
    code = ErrorCode.PARAM_OUT_OF_RANGE


class ParamLocked(MachineError):
    code = ErrorCode.PARAM_LOCKED


class StorageFailed(MachineError):
    code = ErrorCode.STORAGE_FAILED


class DuplicateId(MachineError):
    code = ErrorCode.DUPLICATE_ID


class ConfigError(MachineError):
    """The machine config cannot be loaded; carries every finding."""

    code = ErrorCode.BAD_PAYLOAD
