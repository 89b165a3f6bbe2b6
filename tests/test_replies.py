"""Answering a query leaves nothing of the request behind once the reply is out."""

from __future__ import annotations

import gc
import weakref

import pytest

from badf.protocol import LimitExceededError, MalformedMessageError
from badf.server._replies import answer


class _Query:
    """Stands in for a zenoh.Query: records what was sent."""

    def __init__(self) -> None:
        self.errors: list[bytes] = []
        self.dropped = False

    def reply_err(self, payload: bytes) -> None:
        self.errors.append(payload)

    def drop(self) -> None:
        self.dropped = True


class _Request:
    """Stands in for a large request's bytes (bytes cannot be weakly referenced)."""


@pytest.mark.parametrize("chained", [False, True])
def test_a_refused_request_is_freed_without_the_garbage_collector(chained: bool) -> None:
    """The error answered used to keep its traceback, whose frames held the request: a reference cycle that
    only the garbage collector frees, and a few large allocations seldom run it (twelve refused 4M-point
    queries held 1 GiB in a worker)."""
    seen: list[weakref.ref] = []

    def work():
        request = _Request()
        seen.append(weakref.ref(request))
        if chained:
            try:
                raise ValueError("inner")
            except ValueError:
                raise MalformedMessageError("refused while handling another error") from None
        raise LimitExceededError("the request is too large")

    query = _Query()
    gc.disable()
    try:
        answer(query, "badf/obj/x/query", work)
        assert query.errors and query.dropped
        assert seen[0]() is None, "the refused request is still referenced"
    finally:
        gc.enable()
