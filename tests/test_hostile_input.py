"""Hostile input to the protocol's decoders: thousands of generated messages of every type, valid at first,
then broken on purpose (header fields, descriptors, metadata, lengths, array bytes) and lying about sizes.

What each test holds, for every example:
  * `decode` returns a message of the type asked for, or raises a MessageError subclass with a message;
    nothing else escapes (no struct.error, no MemoryError, no RecursionError, no plain ValueError);
  * where a mutation has one right answer (a cut message, trailing bytes, a wrong magic, version or kind,
    a header claiming more bytes than the limit, a dimension beyond its limit), it is that exact error;
  * decoding allocates at most 64 times the message's own size plus 64 KiB, however large the header says
    the arrays are (tracemalloc sees numpy's buffers as well as Python's objects);
  * a message that does decode is canonical: encoding it again and decoding gives the same message.

The example counts are fixed (no time-based budget) and sum to a little over 4,000 decodes per run.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from hostile_messages import DIMENSIONS, LIMITS, MESSAGES, MUTATIONS, Parts, any_message
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from badf.protocol import (
    MESSAGE_TYPES,
    BadfError,
    ErrorCode,
    Frame,
    LimitExceededError,
    MeshReply,
    MessageError,
    QueryReply,
    QueryRequest,
    RegisterRequest,
    SliceReply,
    decode,
    encode,
    error_for_code,
)
from badf.protocol._wire import WireDtype

# Decoding may allocate this many times the message's own size (the metadata's Python objects are the
# largest part), plus a constant; never anything that grows with the sizes a header claims.
ALLOCATION_FACTOR = 64
ALLOCATION_SLACK = 64 * 1024
MESSAGE_ERROR_CODES = {code for code in ErrorCode if code < ErrorCode.NOT_FOUND}


def assert_same(a: object, b: object) -> None:
    assert type(a) is type(b)
    for name in vars(a):
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape, name
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            assert x == y, name


def decode_within_memory(data: bytes, cls: type):
    """decode(data, cls) under tracemalloc: its result, or the MessageError it raised, and its peak bytes."""
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before, _ = tracemalloc.get_traced_memory()
        try:
            outcome = decode(data, cls, limits=LIMITS)
        except MessageError as error:
            outcome = error
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    allowed = ALLOCATION_FACTOR * len(data) + ALLOCATION_SLACK
    assert peak - before <= allowed, f"decoding {len(data)} bytes allocated {peak - before} (allowed {allowed})"
    return outcome


def check_outcome(outcome: object, cls: type, expected: type[MessageError] | None) -> None:
    """A decoded message of type `cls` (canonical), or a specific, explained MessageError."""
    if isinstance(outcome, MessageError):
        assert outcome.message, "an error without a message"
        assert outcome.code in MESSAGE_ERROR_CODES
        if expected is not None:
            assert type(outcome) is expected, f"expected {expected.__name__}, got {type(outcome).__name__}: {outcome}"
        return
    assert expected is None, f"expected {expected.__name__}, but the message decoded"
    assert type(outcome) is cls
    assert_same(decode(bytes(encode(outcome)), cls, limits=LIMITS), outcome)


# --- the tests ---------------------------------------------------------------------------------------


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(any_message)
def test_generated_messages_round_trip(message) -> None:
    cls = type(message)
    data = bytes(encode(message))
    outcome = decode_within_memory(data, cls)
    if isinstance(outcome, LimitExceededError):  # generated within these limits except message-level sizes
        pytest.fail(f"a generated {cls.__name__} exceeded the test's limits: {outcome}")
    check_outcome(outcome, cls, None)
    assert_same(outcome, message)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(any_message, st.data())
def test_mutated_messages_fail_with_their_own_error(message, data_object) -> None:
    """Every mutation applied, one at a time, to each generated message: 12 broken messages per example."""
    cls = type(message)
    data = bytes(encode(message))
    for name, mutation in MUTATIONS.items():
        broken, expected = mutation(data_object, data, Parts.of(data))
        try:
            check_outcome(decode_within_memory(broken, cls), cls, expected)
        except AssertionError as failure:
            raise AssertionError(f"mutation {name!r} of a {cls.__name__}: {failure}") from None


@st.composite
def lying_headers(draw) -> tuple[type, bytes, type[MessageError] | None, bool]:
    """A valid message whose descriptors now claim up to 2**32 - 1 per axis, with the bytes left as they were."""
    cls = draw(st.sampled_from([cls for cls in MESSAGE_TYPES if cls.SLOTS]))
    parts = Parts.of(bytes(encode(draw(MESSAGES[cls]))))
    present = [index for index, (code, _, _) in enumerate(parts.descriptors) if code != WireDtype.ABSENT]
    assume(present)  # a QueryReply may carry no array at all
    index = draw(st.sampled_from(present))
    code, ndim, dims = parts.descriptors[index]
    named = [axis for axis, dim in enumerate(cls.SLOTS[index].shape) if isinstance(dim, str)]
    claimed = list(dims)
    for axis in draw(st.lists(st.sampled_from(named), min_size=1, unique=True)):
        limit = DIMENSIONS[cls.SLOTS[index].shape[axis]][0]
        claimed[axis] = draw(st.integers(0, 2**32 - 1) | st.integers(limit + 1, 2**32 - 1))
    data = parts.assemble()
    parts.descriptors[index] = (code, ndim, tuple(claimed))
    # A lie the bytes cannot tell from the truth: a (2, 3) grid claimed as (3, 2), or one more row that the
    # zero padding before the next array absorbs. Such a message may decode (padding read as data).
    same_bytes = parts.described_length() == len(data)
    return cls, parts.assemble(), _first_shape_failure(cls, parts), same_bytes


def _first_shape_failure(cls: type, parts: Parts) -> type[MessageError] | None:
    """LimitExceededError if the decoder's shape checks (slot by slot, axis by axis: limit, then minimum,
    then agreement with the arrays before) meet a size beyond its limit first; None if they meet another
    failure first, or none (then the bytes do not match the sizes: a truncated or malformed message)."""
    bound: dict[str, int] = {}
    for slot, (code, ndim, dims) in zip(cls.SLOTS, parts.descriptors):
        if code == WireDtype.ABSENT:
            continue
        for size, dim in zip(dims[:ndim], slot.shape):
            if isinstance(dim, int):
                continue
            limit, minimum = DIMENSIONS[dim]
            if size > limit:
                return LimitExceededError
            if size < minimum or bound.get(dim, size) != size:
                return None
            bound[dim] = size
    return None


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(lying_headers())
def test_lying_headers_fail_before_allocating(case) -> None:
    cls, data, expected, same_bytes = case
    outcome = decode_within_memory(data, cls)
    if not same_bytes:
        assert isinstance(outcome, MessageError), f"a header claiming other sizes than its bytes decoded: {outcome}"
    check_outcome(outcome, cls, expected)


def test_a_billion_elements_on_a_small_payload() -> None:
    """The example of the issue: headers claiming 10^9 rows (12 GB) in every array slot of every type."""
    for cls in MESSAGE_TYPES:
        if not cls.SLOTS:
            continue
        parts = Parts.of(bytes(encode(_smallest(cls))))
        for index, (code, ndim, dims) in enumerate(parts.descriptors):
            if code == WireDtype.ABSENT:
                continue
            lying = Parts(parts.kind, list(parts.descriptors), parts.metadata, list(parts.arrays))
            lying.descriptors[index] = (code, ndim, (1_000_000_000,) + dims[1:])
            outcome = decode_within_memory(lying.assemble(), cls)
            assert isinstance(outcome, LimitExceededError), f"{cls.__name__} slot {index}: {outcome!r}"


def _smallest(cls: type):
    """A message of `cls` with every optional array present, one row each."""
    row = np.zeros((1, 3), np.float32)
    return {
        RegisterRequest: RegisterRequest("a", np.eye(3, dtype=np.float32), np.array([[0, 1, 2]])),
        Frame: Frame("a", 1, row),
        QueryRequest: QueryRequest("a", row),
        QueryReply: QueryReply("a", 0, np.zeros(1), row, row, np.zeros(1, np.int32)),
        SliceReply: SliceReply(
            "a", 0, "x", 0.0, ((0, 0), (1, 1)), np.zeros((1, 1)), np.zeros((1, 2, 3)), np.zeros(1, np.uint8),
            np.zeros(1, np.uint8), row,
        ),  # fmt: skip
        MeshReply: MeshReply("a", 0, np.eye(3, dtype=np.float32), np.array([[0, 1, 2]])),
    }[cls]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=256), st.sampled_from(MESSAGE_TYPES))
def test_arbitrary_bytes_are_refused(data: bytes, cls: type) -> None:
    outcome = decode_within_memory(data, cls)
    assert isinstance(outcome, MessageError)
    check_outcome(outcome, cls, None)


@settings(max_examples=300, deadline=None)
@given(st.integers(-(2**63), 2**63), st.text(max_size=50))
def test_any_error_code_becomes_a_badf_error(code: int, text: str) -> None:
    error = error_for_code(code, text)
    assert isinstance(error, BadfError)
    assert text in error.message
