"""Error codes that travel in error replies, and one exception type per code.

A worker answers a bad request with an `ErrorReply` carrying a code and a human message; the client turns
it back into the exception of that code (`error_for_code`), so both sides raise the same types.
"""

from __future__ import annotations

from enum import IntEnum


class ErrorCode(IntEnum):
    # The message itself is malformed (found while decoding, before anything is allocated or changed).
    TRUNCATED = 1
    MALFORMED = 2
    UNSUPPORTED_VERSION = 3
    WRONG_KIND = 4
    BAD_METADATA = 5
    WRONG_DTYPE = 6
    WRONG_SHAPE = 7
    NOT_FINITE = 8
    INDEX_OUT_OF_RANGE = 9
    LIMIT_EXCEEDED = 10
    INVALID_OPTION = 11
    INVALID_NAME = 12
    # The message is well formed but does not fit the object's state.
    NOT_FOUND = 20
    ALREADY_EXISTS = 21
    STALE_FRAME = 22
    VERTEX_COUNT_MISMATCH = 23
    REJECTED_INPUT = 24
    NOT_SUPPORTED = 25
    BUSY = 26
    # The worker could not be reached or failed.
    UNAVAILABLE = 30
    TIMEOUT = 31
    INTERNAL = 32


class BadfError(Exception):
    """Base of every badf error; `code` says which, `message` says what was expected and what came."""

    code: ErrorCode = ErrorCode.INTERNAL

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class MessageError(BadfError, ValueError):
    """A message failed validation: its bytes, metadata or arrays are not what the protocol allows."""

    code = ErrorCode.MALFORMED


class TruncatedMessageError(MessageError):
    code = ErrorCode.TRUNCATED


class MalformedMessageError(MessageError):
    code = ErrorCode.MALFORMED


class UnsupportedVersionError(MessageError):
    code = ErrorCode.UNSUPPORTED_VERSION


class WrongKindError(MessageError):
    code = ErrorCode.WRONG_KIND


class MetadataError(MessageError):
    code = ErrorCode.BAD_METADATA


class DtypeError(MessageError):
    code = ErrorCode.WRONG_DTYPE


class ShapeError(MessageError):
    code = ErrorCode.WRONG_SHAPE


class NonFiniteError(MessageError):
    code = ErrorCode.NOT_FINITE


class IndexRangeError(MessageError):
    code = ErrorCode.INDEX_OUT_OF_RANGE


class LimitExceededError(MessageError):
    code = ErrorCode.LIMIT_EXCEEDED


class InvalidOptionError(MessageError):
    code = ErrorCode.INVALID_OPTION


class InvalidNameError(MessageError):
    code = ErrorCode.INVALID_NAME


class ObjectNotFoundError(BadfError):
    code = ErrorCode.NOT_FOUND


class ObjectExistsError(BadfError):
    code = ErrorCode.ALREADY_EXISTS


class StaleFrameError(BadfError):
    """A frame numbered at or below the object's newest frame, or superseded before it was applied."""

    code = ErrorCode.STALE_FRAME


class VertexCountMismatchError(BadfError, ValueError):
    code = ErrorCode.VERTEX_COUNT_MISMATCH


class RejectedInputError(BadfError, ValueError):
    """The engine refused well-formed input (for example an option value it does not support)."""

    code = ErrorCode.REJECTED_INPUT


class NotSupportedError(BadfError):
    code = ErrorCode.NOT_SUPPORTED


class WorkerBusyError(BadfError):
    """The object's queue of waiting requests is full; try again later."""

    code = ErrorCode.BUSY


class WorkerUnavailableError(BadfError, ConnectionError):
    """No worker answered: none is running, the object's worker is gone, or it is shutting down."""

    code = ErrorCode.UNAVAILABLE


class ObjectUnavailableError(WorkerUnavailableError):
    """The object's worker is gone (the client saw its liveliness token go): a worker that ended took the object's
    state with it, and `RemoteObject.reregister()` registers it again on another worker from what the handle kept;
    one stalled past Zenoh's lease that resumes still serving it answers the handle again. Raised by the client
    only: on the wire it is UNAVAILABLE."""


class AccessDeniedError(WorkerUnavailableError):
    """The worker (and the object) answer, but not this request: the router did not deliver it, which is what
    Zenoh's access control does, without a word, to a message the client's user is not allowed. Raised by
    the client only, which infers it: on the wire nothing comes back at all."""


class WorkerTimeoutError(BadfError, TimeoutError):
    code = ErrorCode.TIMEOUT


class InternalWorkerError(BadfError):
    code = ErrorCode.INTERNAL


_ERROR_TYPES: dict[ErrorCode, type[BadfError]] = {
    cls.code: cls
    for cls in (
        TruncatedMessageError,
        MalformedMessageError,
        UnsupportedVersionError,
        WrongKindError,
        MetadataError,
        DtypeError,
        ShapeError,
        NonFiniteError,
        IndexRangeError,
        LimitExceededError,
        InvalidOptionError,
        InvalidNameError,
        ObjectNotFoundError,
        ObjectExistsError,
        StaleFrameError,
        VertexCountMismatchError,
        RejectedInputError,
        NotSupportedError,
        WorkerBusyError,
        WorkerUnavailableError,
        WorkerTimeoutError,
        InternalWorkerError,
    )
}


def error_for_code(code: int, message: str) -> BadfError:
    """The exception for an error code received from a worker; an unknown code becomes InternalWorkerError."""
    try:
        return _ERROR_TYPES[ErrorCode(code)](message)
    except ValueError:
        return InternalWorkerError(f"unknown error code {code}: {message}")
