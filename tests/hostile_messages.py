"""Messages for hostile-input tests: generators of valid messages of every type, the wire layout written
out again from protocol/_wire.py's documentation (to take messages apart and put them together wrongly),
and twelve ways of breaking a message, each with the one error it must give where there is one.

Shared by tests/test_hostile_input.py (the decoders alone) and tests/test_hostile_service.py (a worker).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from badf.protocol import (
    AXES,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    QUERY_MODES,
    QUERY_OUTPUTS,
    REFINE_METHODS,
    SIGN_METHODS,
    Deleted,
    DeleteRequest,
    ErrorReply,
    Frame,
    FrameAck,
    InfoRequest,
    LimitExceededError,
    MeshReply,
    MeshRequest,
    Limits,
    MalformedMessageError,
    MessageError,
    MetadataError,
    ObjectInfo,
    ObjectOptions,
    QueryReply,
    QueryRequest,
    RegisterRequest,
    SliceReply,
    SliceRequest,
    TruncatedMessageError,
    UnsupportedVersionError,
    WorkerInfo,
    WrongKindError,
)
from badf.protocol._messages import MAX_HALO
from badf.protocol._wire import NUMPY_DTYPES, WireDtype

HEADER = struct.Struct("<4sHBBIQ")  # magic, version, kind, array count, metadata bytes, total bytes
DESCRIPTOR = struct.Struct("<BBxxIII")  # dtype code, ndim, three sizes
ALIGN = 16
# Small limits, so that generated sizes cross them often (the mutations' expected errors assume them).
LIMITS = Limits(
    max_vertices=64,
    max_faces=96,
    max_points=64,
    max_cells=64,
    max_slice_resolution=32,
    max_message_bytes=1 << 20,
    max_metadata_bytes=64 * 1024,
)
# Each named dimension of a slot: the limit that bounds it and its minimum (protocol/_messages.py).
DIMENSIONS = {
    "N": (LIMITS.max_vertices, 1),
    "M": (LIMITS.max_faces, 1),
    "P": (LIMITS.max_points, 1),
    "K": (LIMITS.max_cells, 0),
    "C": (LIMITS.max_points, 0),
    "H": (LIMITS.max_slice_resolution, 1),
    "W": (LIMITS.max_slice_resolution, 1),
}
# Decoding may allocate this many times the message's own size (the metadata's Python objects are the
# largest part), plus a constant; never anything that grows with the sizes a header claims.
# --- valid messages of every type ----------------------------------------------------------------------

names = st.from_regex(r"[A-Za-z0-9_.\-]{1,24}", fullmatch=True)
frame_numbers = st.integers(0, 2**53)
counts = st.integers(0, 2**40)
finite = st.floats(-1e6, 1e6, allow_nan=False, width=32)
json_scalars = (
    st.none() | st.booleans() | st.integers(-(2**53), 2**53) | st.floats(allow_nan=False, allow_infinity=False)
)
json_values = st.recursive(
    json_scalars | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)
json_objects = st.dictionaries(st.text(max_size=8), json_values, max_size=5)


def float_rows(rows: st.SearchStrategy[int], columns: int = 3) -> st.SearchStrategy[np.ndarray]:
    return rows.flatmap(lambda n: hnp.arrays(np.float32, (n, columns), elements=finite))


@st.composite
def object_options(draw) -> ObjectOptions:
    return ObjectOptions(
        depth=draw(st.integers(1, 10)),
        sign=draw(st.sampled_from(SIGN_METHODS)),
        band=draw(st.none() | st.floats(1e-6, 1e6)),
        coherence=draw(st.booleans()),
        refine=draw(st.sampled_from(REFINE_METHODS)),
        halo=draw(st.integers(0, MAX_HALO)),
        region=draw(st.none() | hnp.arrays(np.float64, (2, 3), elements=finite).map(lambda box: np.sort(box, axis=0))),
    )


@st.composite
def register_requests(draw) -> RegisterRequest:
    vertices = draw(float_rows(st.integers(1, 16)))
    faces = draw(
        st.integers(1, 16).flatmap(lambda m: hnp.arrays(np.int32, (m, 3), elements=st.integers(0, len(vertices) - 1)))
    )
    return RegisterRequest(
        draw(names), vertices, faces, draw(object_options()), frame=draw(frame_numbers), replace=draw(st.booleans())
    )


@st.composite
def object_infos(draw) -> ObjectInfo:
    return ObjectInfo(
        draw(names), draw(names), draw(frame_numbers), draw(counts), draw(counts), draw(object_options()),
        frames_applied=draw(counts), frames_dropped=draw(counts), frames_rejected=draw(counts),
        queries_answered=draw(counts), points_answered=draw(counts), last_error=draw(st.none() | st.text(max_size=40)),
        field_info=draw(json_objects), field_stats=draw(json_objects),
    )  # fmt: skip


@st.composite
def query_requests(draw) -> QueryRequest:
    outputs = draw(st.lists(st.sampled_from(QUERY_OUTPUTS), min_size=1, max_size=4, unique=True))
    return QueryRequest(
        draw(names), draw(float_rows(st.integers(1, 16))), mode=draw(st.sampled_from(QUERY_MODES)), outputs=outputs
    )


@st.composite
def query_replies(draw) -> QueryReply:
    count = draw(st.integers(1, 16))
    present = draw(st.lists(st.sampled_from(QUERY_OUTPUTS), max_size=4, unique=True))
    arrays = {
        "distance": hnp.arrays(np.float32, (count,), elements=finite),
        "closest_point": hnp.arrays(np.float32, (count, 3), elements=finite),
        "normal": hnp.arrays(np.float32, (count, 3), elements=finite),
        "face": hnp.arrays(np.int32, (count,), elements=st.integers(-(2**31), 2**31 - 1)),
    }
    return QueryReply(draw(names), draw(frame_numbers), **{name: draw(arrays[name]) for name in present})


@st.composite
def slice_requests(draw) -> SliceRequest:
    levels = draw(st.none() | st.tuples(st.integers(0, 10), st.integers(0, 10)).map(sorted).map(tuple))
    return SliceRequest(
        draw(names), draw(st.sampled_from(AXES)), draw(finite), resolution=draw(st.integers(1, 32)), levels=levels,
        cells=draw(st.booleans()), corners=draw(st.booleans()),
    )  # fmt: skip


@st.composite
def slice_replies(draw) -> SliceReply:
    rows, columns, cells = draw(st.integers(1, 8)), draw(st.integers(1, 8)), draw(st.integers(0, 8))
    grid = draw(hnp.arrays(np.float32, (rows, columns), elements=finite))
    with_cells = draw(st.booleans())
    extras = {}
    if with_cells:
        extras = {
            "cell_boxes": draw(hnp.arrays(np.float32, (cells, 2, 3), elements=finite)),
            "cell_levels": draw(hnp.arrays(np.uint8, (cells,))),
            "cell_flags": draw(hnp.arrays(np.uint8, (cells,))),
        }
    if draw(st.booleans()):
        extras["corner_points"] = draw(float_rows(st.integers(0, 8)))
    low = (draw(finite), draw(finite))
    high = (draw(finite), draw(finite))
    return SliceReply(
        draw(names), draw(frame_numbers), draw(st.sampled_from(AXES)), draw(finite), (low, high), grid, **extras
    )


@st.composite
def mesh_replies(draw) -> MeshReply:
    vertices = draw(float_rows(st.integers(1, 16)))
    faces = None
    if draw(st.booleans()):
        faces = draw(
            st.integers(1, 16).flatmap(
                lambda m: hnp.arrays(np.int32, (m, 3), elements=st.integers(0, len(vertices) - 1))
            )
        )
    return MeshReply(draw(names), draw(frame_numbers), vertices, faces)


limits_maps = st.dictionaries(st.text(max_size=12), st.integers(0, 2**40), max_size=7)
MESSAGES: dict[type, st.SearchStrategy] = {
    RegisterRequest: register_requests(),
    ObjectInfo: object_infos(),
    Frame: st.builds(Frame, names, frame_numbers, float_rows(st.integers(1, 16)),
                     registration=st.none() | frame_numbers),
    FrameAck: st.builds(FrameAck, names, frame_numbers),
    QueryRequest: query_requests(),
    QueryReply: query_replies(),
    SliceRequest: slice_requests(),
    SliceReply: slice_replies(),
    MeshRequest: st.builds(MeshRequest, names, st.booleans()),
    MeshReply: mesh_replies(),
    InfoRequest: st.builds(InfoRequest, st.none() | names),
    WorkerInfo: st.builds(
        WorkerInfo, names, st.text(max_size=12), counts, counts, counts, st.floats(0, 1e9), limits_maps
    ),
    DeleteRequest: st.builds(DeleteRequest, names),
    Deleted: st.builds(Deleted, names, frame_numbers),
    ErrorReply: st.builds(ErrorReply, st.integers(0, 65535), st.text(max_size=200)),
}
assert set(MESSAGES) == set(MESSAGE_TYPES), "a message type has no generator"
any_message = st.one_of(list(MESSAGES.values()))


# --- the layout, written out again from the documentation in protocol/_wire.py ---------------------------


@dataclass
class Parts:
    """A message taken apart: header fields, descriptors (code, ndim, dims), metadata bytes, array bytes."""

    kind: int
    descriptors: list[tuple[int, int, tuple[int, int, int]]]
    metadata: bytes
    arrays: list[bytes]
    magic: bytes = b"BADF"
    version: int = PROTOCOL_VERSION

    @classmethod
    def of(cls, data: bytes) -> Parts:
        magic, version, kind, array_count, metadata_size, total = HEADER.unpack_from(data, 0)
        descriptors, arrays = [], []
        for index in range(array_count):
            code, ndim, *dims = DESCRIPTOR.unpack_from(data, HEADER.size + DESCRIPTOR.size * index)
            descriptors.append((code, ndim, tuple(dims)))
        offset = HEADER.size + DESCRIPTOR.size * array_count
        metadata = data[offset : offset + metadata_size]
        offset += metadata_size
        for code, ndim, dims in descriptors:
            if code == WireDtype.ABSENT:
                arrays.append(b"")
                continue
            offset = -(-offset // ALIGN) * ALIGN
            size = math.prod(dims[:ndim]) * NUMPY_DTYPES[WireDtype(code)].itemsize
            arrays.append(data[offset : offset + size])
            offset += size
        assert offset == total == len(data)
        return cls(kind, descriptors, metadata, arrays, magic, version)

    def described_length(self) -> int:
        """The message length the header and descriptors describe (arrays start at multiples of 16)."""
        offset = HEADER.size + DESCRIPTOR.size * len(self.descriptors) + len(self.metadata)
        for code, ndim, dims in self.descriptors:
            if code != WireDtype.ABSENT:
                offset = -(-offset // ALIGN) * ALIGN + math.prod(dims[:ndim]) * NUMPY_DTYPES[WireDtype(code)].itemsize
        return offset

    def assemble(self, *, total: int | None = None, metadata_size: int | None = None) -> bytes:
        """The bytes of these parts; `total` and `metadata_size` override the header's honest values."""
        body = bytearray(HEADER.size + DESCRIPTOR.size * len(self.descriptors))
        for index, (code, ndim, dims) in enumerate(self.descriptors):
            DESCRIPTOR.pack_into(body, HEADER.size + DESCRIPTOR.size * index, code, ndim, *dims)
        body += self.metadata
        for (code, _, _), array in zip(self.descriptors, self.arrays):
            if code != WireDtype.ABSENT:  # present, if maybe empty: it still starts at a multiple of 16
                body += bytes(-len(body) % ALIGN) + array
        HEADER.pack_into(
            body, 0, self.magic, self.version, self.kind, len(self.descriptors) % 256,
            len(self.metadata) if metadata_size is None else metadata_size, len(body) if total is None else total,
        )  # fmt: skip
        return bytes(body)


# Each mutation: (name, how it breaks the parts or bytes, the one error it must give or None for "any").
Mutation = Callable[[st.DataObject, bytes, Parts], tuple[bytes, type[MessageError] | None]]


def _cut(data_object, data, parts):
    return data[: data_object.draw(st.integers(0, len(data) - 1))], TruncatedMessageError


def _trailing(data_object, data, parts):
    return data + data_object.draw(st.binary(min_size=1, max_size=64)), MalformedMessageError


def _magic(data_object, data, parts):
    parts.magic = data_object.draw(st.binary(min_size=4, max_size=4).filter(lambda m: m != b"BADF"))
    return parts.assemble(), MalformedMessageError


def _version(data_object, data, parts):
    parts.version = data_object.draw(st.integers(0, 65535).filter(lambda v: v != PROTOCOL_VERSION))
    return parts.assemble(), UnsupportedVersionError


def _kind(data_object, data, parts):
    parts.kind = data_object.draw(st.integers(0, 255).filter(lambda k: k != parts.kind))
    return parts.assemble(), WrongKindError


def _total(data_object, data, parts):
    total = data_object.draw(st.integers(0, 2**64 - 1).filter(lambda t: t != len(data)))
    if total > LIMITS.max_message_bytes:
        expected = LimitExceededError
    else:
        expected = TruncatedMessageError if total > len(data) else MalformedMessageError
    return parts.assemble(total=total), expected


def _metadata_size(data_object, data, parts):
    size = data_object.draw(st.integers(0, 2**32 - 1).filter(lambda s: s != len(parts.metadata)))
    return parts.assemble(metadata_size=size), LimitExceededError if size > LIMITS.max_metadata_bytes else None


def _array_count(data_object, data, parts):
    count = data_object.draw(st.integers(0, 255).filter(lambda c: c != len(parts.descriptors)))
    out = bytearray(data)
    out[7] = count
    return bytes(out), None


def _descriptor_field(data_object, data, parts):
    if not parts.descriptors:
        return _array_count(data_object, data, parts)
    index = data_object.draw(st.integers(0, len(parts.descriptors) - 1))
    code, ndim, dims = parts.descriptors[index]
    field = data_object.draw(st.sampled_from(["code", "ndim", "dim"]))
    if field == "code":
        code = data_object.draw(st.integers(0, 255))
    elif field == "ndim":
        ndim = data_object.draw(st.integers(0, 255))
    else:
        axis = data_object.draw(st.integers(0, 2))
        dims = tuple(data_object.draw(st.integers(0, 2**32 - 1)) if a == axis else d for a, d in enumerate(dims))
    out = bytearray(data)
    DESCRIPTOR.pack_into(out, HEADER.size + DESCRIPTOR.size * index, code, ndim, *dims)
    return bytes(out), None


def _metadata_value(data_object, data, parts):
    metadata = json.loads(parts.metadata)
    key = data_object.draw(st.sampled_from(sorted(metadata) or ["name"]))
    action = data_object.draw(st.sampled_from(["drop", "replace", "add"]))
    if action == "drop":
        metadata.pop(key, None)
    elif action == "replace":
        metadata[key] = data_object.draw(json_values)
    else:
        metadata[data_object.draw(st.text(max_size=8))] = data_object.draw(json_values)
    parts.metadata = json.dumps(metadata).encode()
    return parts.assemble(), None


def _metadata_bytes(data_object, data, parts):
    """Metadata that is not a JSON object: broken UTF-8, NaN, a list, deep nesting, or any bytes."""
    raw = data_object.draw(
        st.sampled_from([b"\xff\xfe{}", b'{"name": NaN}', b"[1, 2]", b"null", b"", b"[" * 5000 + b"]" * 5000])
        | st.binary(max_size=64).filter(lambda b: not _is_json_object(b))
    )
    parts.metadata = raw
    return parts.assemble(), MetadataError if len(raw) <= LIMITS.max_metadata_bytes else LimitExceededError


def _is_json_object(raw: bytes) -> bool:
    try:
        return isinstance(json.loads(raw), dict)
    except (ValueError, RecursionError):
        return False


def _array_bytes(data_object, data, parts):
    present = [index for index, array in enumerate(parts.arrays) if array]
    if not present:
        return _metadata_value(data_object, data, parts)
    index = data_object.draw(st.sampled_from(present))
    array = bytearray(parts.arrays[index])
    for _ in range(data_object.draw(st.integers(1, 4))):
        at = data_object.draw(st.integers(0, len(array) - 1))
        chunk = data_object.draw(
            st.sampled_from([b"\x00\x00\xc0\x7f", b"\x00\x00\x80\x7f", b"\xff\xff\xff\xff", b"\xff\xff\xff\x7f"])
        )
        array[at : at + 4] = chunk[: len(array) - at]
    parts.arrays[index] = bytes(array)
    return parts.assemble(), None


MUTATIONS: dict[str, Mutation] = {
    "cut": _cut,
    "trailing": _trailing,
    "magic": _magic,
    "version": _version,
    "kind": _kind,
    "total": _total,
    "metadata_size": _metadata_size,
    "array_count": _array_count,
    "descriptor": _descriptor_field,
    "metadata_value": _metadata_value,
    "metadata_bytes": _metadata_bytes,
    "array_bytes": _array_bytes,
}
