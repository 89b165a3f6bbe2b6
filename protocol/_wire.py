"""The byte layout every message shares: a fixed header, array descriptors, JSON metadata, raw arrays.

    offset 0    header, 20 bytes, little-endian:
                magic b"BADF" | version u16 | kind u8 | array_count u8 | metadata_bytes u32 | total_bytes u64
    offset 20   array_count descriptors of 16 bytes: dtype u8 | ndim u8 | 2 zero bytes | 3 x dim u32
                (dtype 0 marks an absent array, with ndim 0; dims past ndim are 0)
    then        the metadata: a UTF-8 JSON object, metadata_bytes long
    then        each present array's raw little-endian C-order bytes, starting at a multiple of 16
                (zero padding before it); the message ends with the last array's last byte

`unpack` checks every size in the header against the limits and against the message's length before it
creates a single array, and the arrays it returns are read-only views into the message (no copy).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Callable, Sequence

import numpy as np

from badf.protocol._errors import (
    DtypeError,
    LimitExceededError,
    MalformedMessageError,
    MetadataError,
    ShapeError,
    TruncatedMessageError,
    UnsupportedVersionError,
)
from badf.protocol._limits import Limits

PROTOCOL_VERSION = 1
MAGIC = b"BADF"
MAX_NDIM = 3
_ALIGN = 16
_HEADER = struct.Struct("<4sHBBIQ")
_DESCRIPTOR = struct.Struct("<BBxxIII")
_MAX_DIM = 2**32 - 1


class WireDtype(IntEnum):
    ABSENT = 0
    FLOAT32 = 1
    FLOAT64 = 2
    INT32 = 3
    INT64 = 4
    UINT32 = 5
    UINT8 = 6


NUMPY_DTYPES: dict[WireDtype, np.dtype] = {
    WireDtype.FLOAT32: np.dtype("<f4"),
    WireDtype.FLOAT64: np.dtype("<f8"),
    WireDtype.INT32: np.dtype("<i4"),
    WireDtype.INT64: np.dtype("<i8"),
    WireDtype.UINT32: np.dtype("<u4"),
    WireDtype.UINT8: np.dtype("u1"),
}
_WIRE_DTYPES = {dtype.newbyteorder("="): code for code, dtype in NUMPY_DTYPES.items()}
_CODES = frozenset(int(code) for code in WireDtype)


@dataclass(frozen=True)
class Descriptor:
    dtype: WireDtype
    shape: tuple[int, ...] | None  # None when the array is absent


@dataclass(frozen=True)
class RawMessage:
    kind: int
    metadata: dict[str, Any]
    descriptors: tuple[Descriptor, ...]
    arrays: tuple[np.ndarray | None, ...]


def _aligned(offset: int) -> int:
    return -(-offset // _ALIGN) * _ALIGN


def _layout(start: int, descriptors: Sequence[Descriptor]) -> tuple[list[int], int]:
    """Byte offset of each present array (-1 for absent ones) and the message's total length."""
    offsets, offset = [], start
    for descriptor in descriptors:
        if descriptor.shape is None:
            offsets.append(-1)
            continue
        offset = _aligned(offset)
        offsets.append(offset)
        offset += math.prod(descriptor.shape) * NUMPY_DTYPES[descriptor.dtype].itemsize
    return offsets, offset


def pack(kind: int, metadata: dict[str, Any], arrays: Sequence[np.ndarray | None]) -> bytearray:
    """One message as bytes. Arrays must already have a wire dtype; they are copied once, into the result."""
    try:
        metadata_bytes = json.dumps(metadata, separators=(",", ":"), allow_nan=False).encode()
    except (TypeError, ValueError) as error:
        raise MetadataError(f"metadata is not finite JSON: {error}") from None
    descriptors = []
    for index, array in enumerate(arrays):
        if array is None:
            descriptors.append(Descriptor(WireDtype.ABSENT, None))
            continue
        code = _WIRE_DTYPES.get(array.dtype.newbyteorder("="))
        if code is None:
            raise DtypeError(f"array {index} has dtype {array.dtype}, which has no wire encoding")
        if array.ndim > MAX_NDIM or any(dim > _MAX_DIM for dim in array.shape):
            raise ShapeError(f"array {index} has shape {array.shape}; at most {MAX_NDIM} axes of < 2**32 fit")
        descriptors.append(Descriptor(code, tuple(array.shape)))
    start = _HEADER.size + _DESCRIPTOR.size * len(descriptors) + len(metadata_bytes)
    offsets, total = _layout(start, descriptors)
    buffer = bytearray(total)
    _HEADER.pack_into(buffer, 0, MAGIC, PROTOCOL_VERSION, kind, len(descriptors), len(metadata_bytes), total)
    for index, descriptor in enumerate(descriptors):
        dims = (descriptor.shape or ()) + (0,) * (MAX_NDIM - len(descriptor.shape or ()))
        ndim = 0 if descriptor.shape is None else len(descriptor.shape)
        _DESCRIPTOR.pack_into(buffer, _HEADER.size + _DESCRIPTOR.size * index, descriptor.dtype, ndim, *dims)
    metadata_start = _HEADER.size + _DESCRIPTOR.size * len(descriptors)
    buffer[metadata_start : metadata_start + len(metadata_bytes)] = metadata_bytes
    for array, descriptor, offset in zip(arrays, descriptors, offsets):
        if array is None or array.size == 0:
            continue
        wire_dtype = NUMPY_DTYPES[descriptor.dtype]
        target = np.frombuffer(buffer, dtype=wire_dtype, count=array.size, offset=offset)
        target[:] = array.reshape(-1)
    return buffer


def unpack(
    data: bytes | bytearray,
    limits: Limits,
    inspect: Callable[[int, tuple[Descriptor, ...]], None] | None = None,
) -> RawMessage:
    """Split a message into metadata and array views, checking every header field before creating an array.

    `inspect(kind, descriptors)` runs as soon as the descriptors are read, before the sizes they imply are
    computed, so the caller's per-kind checks (array count, dtypes, shapes, count limits) come first.
    """
    size = len(data)
    if size > limits.max_message_bytes:
        raise LimitExceededError(f"message is {size} bytes; the limit is {limits.max_message_bytes}")
    if size < _HEADER.size:
        raise TruncatedMessageError(f"message is {size} bytes; its header alone needs {_HEADER.size}")
    magic, version, kind, array_count, metadata_size, total = _HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise MalformedMessageError(f"not a badf message: starts with {bytes(magic)!r}, expected {MAGIC!r}")
    if version != PROTOCOL_VERSION:
        raise UnsupportedVersionError(f"message has protocol version {version}; this side speaks {PROTOCOL_VERSION}")
    if total > limits.max_message_bytes:
        raise LimitExceededError(f"header announces {total} bytes; the limit is {limits.max_message_bytes}")
    if size < total:
        raise TruncatedMessageError(f"message is {size} bytes but its header says {total}")
    if size > total:
        raise MalformedMessageError(f"message is {size} bytes but its header says {total}: trailing bytes")
    if metadata_size > limits.max_metadata_bytes:
        raise LimitExceededError(f"metadata is {metadata_size} bytes; the limit is {limits.max_metadata_bytes}")
    metadata_start = _HEADER.size + _DESCRIPTOR.size * array_count
    if metadata_start + metadata_size > total:
        raise TruncatedMessageError(
            f"header announces {array_count} arrays and {metadata_size} metadata bytes, "
            f"which need {metadata_start + metadata_size} bytes; the message has {total}"
        )
    descriptors = tuple(_read_descriptor(data, index) for index in range(array_count))
    if inspect is not None:
        inspect(kind, descriptors)
    offsets, needed = _layout(metadata_start + metadata_size, descriptors)
    if needed > total:
        raise TruncatedMessageError(f"the arrays described in the header need {needed} bytes; the message has {total}")
    if needed < total:
        raise MalformedMessageError(f"the header describes {needed} bytes; the message has {total}: trailing bytes")
    metadata = _read_metadata(bytes(data[metadata_start : metadata_start + metadata_size]))
    arrays = tuple(
        None
        if descriptor.shape is None
        else np.frombuffer(
            data, dtype=NUMPY_DTYPES[descriptor.dtype], count=math.prod(descriptor.shape), offset=offset
        ).reshape(descriptor.shape)
        for descriptor, offset in zip(descriptors, offsets)
    )
    return RawMessage(kind, metadata, descriptors, arrays)


def _read_descriptor(data: bytes | bytearray, index: int) -> Descriptor:
    code, ndim, *dims = _DESCRIPTOR.unpack_from(data, _HEADER.size + _DESCRIPTOR.size * index)
    if code not in _CODES:
        raise DtypeError(f"array {index} has dtype code {code}, which is not one of {[int(c) for c in WireDtype]}")
    if ndim > MAX_NDIM:
        raise ShapeError(f"array {index} has {ndim} axes; at most {MAX_NDIM} are allowed")
    if any(dims[ndim:]):
        raise MalformedMessageError(f"array {index} has {ndim} axes but nonzero sizes past them: {dims}")
    if code == WireDtype.ABSENT:
        if ndim:
            raise MalformedMessageError(f"array {index} is marked absent but has {ndim} axes")
        return Descriptor(WireDtype.ABSENT, None)
    return Descriptor(WireDtype(code), tuple(dims[:ndim]))


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a finite number")


def _read_metadata(raw: bytes) -> dict[str, Any]:
    try:
        metadata = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as error:
        raise MetadataError(f"metadata is not valid JSON: {error}") from None
    if not isinstance(metadata, dict):
        raise MetadataError(f"metadata must be a JSON object, got {type(metadata).__name__}")
    return metadata
