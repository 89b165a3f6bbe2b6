"""Answering Zenoh queries: one reply or one error reply per query, then the query is finished."""

from __future__ import annotations

import logging
from contextlib import contextmanager
from typing import Callable, Iterator

import zenoh

from badf.protocol import (
    BadfError,
    ErrorReply,
    InternalWorkerError,
    LimitExceededError,
    Limits,
    MalformedMessageError,
    Message,
    RejectedInputError,
    encode,
)

log = logging.getLogger("badf.server")


def request_bytes(payload: zenoh.ZBytes | None, limits: Limits) -> bytes:
    """The payload's bytes, refused by size before they are copied out of Zenoh."""
    if payload is None or len(payload) == 0:
        raise MalformedMessageError("the request carries no payload; expected a badf message")
    if len(payload) > limits.max_message_bytes:
        raise LimitExceededError(f"message is {len(payload)} bytes; the limit is {limits.max_message_bytes}")
    return payload.to_bytes()


def reply_error(query: zenoh.Query, error: BadfError) -> None:
    try:
        query.reply_err(encode(ErrorReply(int(error.code), error.message)))
    except zenoh.ZError as failure:  # the asker is gone; nothing is waiting for this answer
        log.debug("could not send an error reply: %s", failure)


def answer(
    query: zenoh.Query,
    key: str,
    work: Callable[[], Message],
    on_error: Callable[[BadfError], None] | None = None,
) -> None:
    """Reply to `query` on `key` with what `work` returns, or with the error it raised; then finish the query.

    `on_error` sees the error before the reply goes out, so whoever gets the error reply also finds it
    counted. An exception that is not a BadfError is a bug on this side: it is logged with its traceback
    and answered as an internal error.
    """
    error: BadfError | None = None
    try:
        payload = encode(work())
    except BadfError as raised:
        error = _detached(raised)
    except Exception as raised:  # noqa: BLE001 - the worker must answer and keep serving
        log.exception("internal error while answering %s", key)
        error = InternalWorkerError(f"internal error on the worker: {type(raised).__name__}: {raised}")
    if error is not None and on_error is not None:
        on_error(error)
    try:
        if error is None:
            try:
                query.reply(key, payload)
            except zenoh.ZError as failure:
                log.debug("could not reply on %s: %s", key, failure)
        else:
            reply_error(query, error)
    finally:
        query.drop()


def _detached(error: BadfError) -> BadfError:
    """The error without its traceback and chained exceptions. Kept past its `except` block, the traceback's
    frames (and so the request's bytes, the query and its Zenoh payload) would live on in a reference cycle
    until the garbage collector next ran, which allocations of a few large buffers seldom set off: twelve
    refused 4M-point queries held 1 GiB in the worker (found by an outside check, 2026-11-22)."""
    error.__traceback__ = None
    error.__context__ = None
    error.__cause__ = None
    return error


def refuse(query: zenoh.Query, error: BadfError) -> None:
    """Answer `query` with `error` and finish it."""
    try:
        reply_error(query, error)
    finally:
        query.drop()


@contextmanager
def engine_errors() -> Iterator[None]:
    """The engine's InvalidInputError (a ValueError) and DeviceMemoryError (a request larger than the device
    holds) become RejectedInputError with the engine's message."""
    try:
        yield
    except BadfError:
        raise
    except (ValueError, MemoryError) as error:
        raise RejectedInputError(str(error)) from None
