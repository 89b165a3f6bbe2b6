"""Every message badf sends, as typed dataclasses, and `encode` / `decode` between them and bytes.

A message is valid by construction: its constructor checks names, options, shapes, dtypes, finiteness and
index ranges, and converts arrays to the canonical dtypes (float32 coordinates, int32 indices, uint8
levels); vertices and query points given as float64 stay float64, so far from the origin they keep their
precision on the way to the engine, which recentres them in float64. `decode` adds what only the receiver
knows: the sizes in the header against its `Limits`, checked before any array is created, and the dtypes
the wire allows. Every failure raises a `MessageError`
subclass whose message says what was expected and what came.

Shapes below use N vertices, M faces, P points, K octree cells, C corner points, H x W grid samples.
Arrays decoded from a message are read-only views into the message's bytes when their dtype is canonical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, ClassVar, Literal, TypeVar, get_args

import numpy as np

from badf.protocol._errors import (
    DtypeError,
    IndexRangeError,
    InvalidOptionError,
    LimitExceededError,
    MalformedMessageError,
    MetadataError,
    NonFiniteError,
    ShapeError,
    WrongKindError,
)
from badf.protocol._keys import check_name
from badf.protocol._limits import DEFAULT_LIMITS, Limits
from badf.protocol._wire import NUMPY_DTYPES, Descriptor, WireDtype, pack, unpack

SignMethod = Literal["auto", "pseudonormal", "winding", "none"]
RefineMethod = Literal["surface", "centroid"]
BvhShape = Literal["auto", "morton", "sah"]
QueryMode = Literal["adf", "exact"]
QueryOutput = Literal["distance", "closest_point", "normal", "face"]
Axis = Literal["x", "y", "z"]

SIGN_METHODS: tuple[str, ...] = get_args(SignMethod)
REFINE_METHODS: tuple[str, ...] = get_args(RefineMethod)
BVH_SHAPES: tuple[str, ...] = get_args(BvhShape)
RigidMode = Literal["auto", "off"]
RIGID_MODES: tuple[str, ...] = get_args(RigidMode)
QUERY_MODES: tuple[str, ...] = get_args(QueryMode)
QUERY_OUTPUTS: tuple[str, ...] = get_args(QueryOutput)
AXES: tuple[str, ...] = get_args(Axis)
# Sanity bounds checked on decode; the engine enforces its own, narrower ranges (RejectedInputError).
MAX_DEPTH = 10  # the engine's deepest octree (badf.server.adf), so a client is told the range that works
MAX_HALO = 2  # the engine's widest halo, likewise (a halo of 3 to 8 passed the client and the worker refused it)
# Not checked on decode: the engine's largest coordinate magnitude (its squares must stay within float32),
# which the client checks a frame against before it sends or keeps it
MAX_COORDINATE = 1.0e18
MAX_ERROR_MESSAGE_LENGTH = 4000
# Bits of SliceReply.cell_flags.
CELL_LEAF = 1
CELL_EMPTY = 2


class MessageKind(IntEnum):
    REGISTER = 1
    OBJECT_INFO = 2
    FRAME = 3
    FRAME_ACK = 4
    QUERY = 5
    QUERY_REPLY = 6
    SLICE_REQUEST = 7
    SLICE_REPLY = 8
    INFO_REQUEST = 9
    WORKER_INFO = 10
    DELETE_REQUEST = 11
    DELETED = 12
    ERROR = 13
    MESH_REQUEST = 14
    MESH_REPLY = 15


# --- arrays: slots, named dimensions, canonical dtypes -------------------------------------------------

Element = Literal["float", "index", "level"]

# A named dimension: the Limits field that bounds it, its minimum, and what it counts (for messages).
_DIMENSIONS: dict[str, tuple[str, int, str]] = {
    "N": ("max_vertices", 1, "vertices"),
    "M": ("max_faces", 1, "faces"),
    "P": ("max_points", 0, "points"),  # an empty batch is answered with empty arrays, as in-process
    "K": ("max_cells", 0, "cells"),
    "C": ("max_points", 0, "corner points"),
    "H": ("max_slice_resolution", 1, "grid rows"),
    "W": ("max_slice_resolution", 1, "grid columns"),
}
_CANONICAL: dict[str, np.dtype] = {
    "float": np.dtype(np.float32),
    "index": np.dtype(np.int32),
    "level": np.dtype(np.uint8),
}
_LOCAL_KINDS: dict[str, str] = {"float": "fiu", "index": "iu", "level": "iu"}
_WIRE_ACCEPTS: dict[str, tuple[WireDtype, ...]] = {
    "float": (WireDtype.FLOAT32, WireDtype.FLOAT64),
    "index": (WireDtype.INT32, WireDtype.INT64, WireDtype.UINT32),
    "level": (WireDtype.UINT8,),
}
_INTEGER_RANGE: dict[str, tuple[int, int]] = {"index": (-(2**31), 2**31 - 1), "level": (0, 255)}


@dataclass(frozen=True)
class _Slot:
    name: str
    element: Element
    shape: tuple[str | int, ...]
    optional: bool = False
    finite: bool = False
    # coordinates given as float64 stay float64, on the wire too: the engine recentres them in float64, so a
    # mesh far from the origin keeps its precision (float32 at 1e5 is 0.008 apart)
    keeps_float64: bool = False

    @property
    def shape_text(self) -> str:
        return "(" + ", ".join(str(dim) for dim in self.shape) + ("," if len(self.shape) == 1 else "") + ")"


def _check_shapes(
    owner: str, slots: tuple[_Slot, ...], shapes: list[tuple[int, ...] | None], limits: Limits | None
) -> None:
    """Shapes against the slots: axis count, fixed sizes, named sizes agreeing across arrays, and limits."""
    bound: dict[str, tuple[int, str]] = {}
    for slot, shape in zip(slots, shapes):
        if shape is None:
            if not slot.optional:
                raise ShapeError(f"{owner} needs {slot.name} of shape {slot.shape_text}, which is missing")
            continue
        if len(shape) != len(slot.shape):
            raise ShapeError(f"{owner}.{slot.name} must have shape {slot.shape_text}, got {tuple(shape)}")
        for size, dim in zip(shape, slot.shape):
            if isinstance(dim, int):
                if size != dim:
                    raise ShapeError(f"{owner}.{slot.name} must have shape {slot.shape_text}, got {tuple(shape)}")
                continue
            limit_name, minimum, noun = _DIMENSIONS[dim]
            if limits is not None and size > getattr(limits, limit_name):
                raise LimitExceededError(
                    f"{owner}.{slot.name} has {size} {noun}; the limit ({limit_name}) is {getattr(limits, limit_name)}"
                )
            if size < minimum:
                raise ShapeError(f"{owner}.{slot.name} has {size} {noun}; at least {minimum} are needed")
            if dim in bound and bound[dim][0] != size:
                other_size, other = bound[dim]
                raise ShapeError(f"{owner}.{slot.name} has {size} {noun} but {owner}.{other} has {other_size}")
            bound[dim] = (size, slot.name)


def _canonical(owner: str, slot: _Slot, array: np.ndarray) -> np.ndarray:
    """`array` in the slot's canonical dtype, C-ordered; no copy when it already is."""
    if array.dtype.kind == "O" and array.size and all(type(x) in (int, float) for x in array.flat):
        # Python ints past 64 bits leave numpy an object array: tell the value, not only "got object"
        big = max((x for x in array.flat if type(x) is int), key=abs, default=0)
        if abs(big) >= 2**63:
            error = IndexRangeError if slot.element != "float" else DtypeError
            raise error(f"{owner}.{slot.name} holds an integer past 64 bits (one of {abs(big).bit_length()} bits)")
    if array.dtype.kind not in _LOCAL_KINDS[slot.element]:
        wanted = "numbers" if slot.element == "float" else "integers"
        raise DtypeError(f"{owner}.{slot.name} must hold {wanted} ({_CANONICAL[slot.element]}), got {array.dtype}")
    canonical = _CANONICAL[slot.element]
    if slot.keeps_float64 and array.dtype == np.float64:
        canonical = array.dtype
    if slot.element != "float" and array.dtype != canonical and array.size:
        low, high = _INTEGER_RANGE[slot.element]
        smallest, largest = int(array.min()), int(array.max())
        if smallest < low or largest > high:
            raise IndexRangeError(
                f"{owner}.{slot.name} holds values in [{smallest}, {largest}], outside {canonical}'s [{low}, {high}]"
            )
    with np.errstate(over="ignore"):  # float64 beyond float32's range becomes inf, reported just below
        result = np.ascontiguousarray(array, dtype=canonical)
    if slot.finite:
        finite = np.isfinite(result)
        if not finite.all():
            bad = np.flatnonzero(~finite.reshape(len(result), -1).all(axis=1))
            converted = " after conversion to float32" if array.dtype != canonical else ""
            raise NonFiniteError(
                f"{owner}.{slot.name} has {len(bad)} rows with NaN or infinite values{converted} (first: row {bad[0]})"
            )
    return result


def _canonical_arrays(message: _Message) -> None:
    owner = type(message).__name__
    arrays: list[np.ndarray | None] = []
    for slot in message.SLOTS:
        value = getattr(message, slot.name)
        if value is None:
            arrays.append(None)
            continue
        try:
            arrays.append(np.asarray(value))
        except ValueError as error:
            raise ShapeError(f"{owner}.{slot.name} is not a rectangular array: {error}") from None
    _check_shapes(owner, message.SLOTS, [None if a is None else a.shape for a in arrays], None)
    for slot, array in zip(message.SLOTS, arrays):
        if array is not None:
            object.__setattr__(message, slot.name, _canonical(owner, slot, array))


# --- metadata: typed reads and value checks ----------------------------------------------------------


class _Fields:
    """Typed access to a decoded message's JSON metadata; a missing or mistyped field is a MetadataError."""

    def __init__(self, owner: str, metadata: dict[str, Any]) -> None:
        self._owner = owner
        self._metadata = metadata

    def _get(self, key: str, types: tuple[type, ...], wanted: str, optional: bool) -> Any:
        value = self._metadata.get(key)
        if value is None:
            if optional:
                return None
            raise MetadataError(f"{self._owner} metadata lacks {key!r} ({wanted})")
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
            raise MetadataError(f"{self._owner} metadata {key!r} must be {wanted}, got {_short(value)}")
        return value

    def text(self, key: str, *, optional: bool = False) -> str:
        return self._get(key, (str,), "a string", optional)

    def integer(self, key: str, *, optional: bool = False) -> int:
        return self._get(key, (int,), "an integer", optional)

    def number(self, key: str, *, optional: bool = False) -> float | None:
        value = self._get(key, (int, float), "a number", optional)
        return None if value is None else float(value)

    def flag(self, key: str) -> bool:
        return self._get(key, (bool,), "true or false", False)

    def mapping(self, key: str) -> dict[str, Any]:
        return self._get(key, (dict,), "an object", False)

    def nested(self, key: str) -> _Fields:
        return _Fields(f"{self._owner}.{key}", self.mapping(key))

    def items(self, key: str, item_types: tuple[type, ...], wanted: str, *, optional: bool = False) -> tuple | None:
        values = self._get(key, (list,), f"a list of {wanted}", optional)
        if values is None:
            return None
        for value in values:
            if not isinstance(value, item_types) or (isinstance(value, bool) and bool not in item_types):
                raise MetadataError(f"{self._owner} metadata {key!r} must be a list of {wanted}, got {_short(values)}")
        return tuple(values)


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


# Integers on the wire (frame numbers, counters) fit a signed 64-bit integer, as clients in other languages
# hold them
MAX_WIRE_INT = 2**63 - 1


def _check_int(owner: str, name: str, value: object, *, minimum: int = 0, maximum: int = MAX_WIRE_INT) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool):
        raise InvalidOptionError(f"{owner}.{name} must be an integer, got {_short(value)}")
    if value < minimum or value > maximum:
        given = str(value) if abs(value) < 10**30 else f"an integer of {int(value).bit_length()} bits"
        # a field bounded only by the wire: its real limit is the worker's, so tell the minimum alone
        if value < minimum and maximum == MAX_WIRE_INT:
            raise InvalidOptionError(f"{owner}.{name} must be at least {minimum}, got {given}")
        raise InvalidOptionError(f"{owner}.{name} must be between {minimum} and {maximum}, got {given}")
    return int(value)


def _check_choice(owner: str, name: str, value: object, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise InvalidOptionError(f"{owner}.{name} must be one of {', '.join(choices)}; got {_short(value)}")
    return value  # type: ignore[return-value]


def _check_flag(owner: str, name: str, value: object) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidOptionError(f"{owner}.{name} must be True or False, got {_short(value)}")
    return bool(value)


def _check_number(owner: str, name: str, value: object, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidOptionError(f"{owner}.{name} must be a number, got {_short(value)}")
    if not math.isfinite(value) or (positive and value <= 0):
        raise InvalidOptionError(
            f"{owner}.{name} must be a finite{' positive' if positive else ''} number, got {value}"
        )
    return float(value)


def _check_box(owner: str, name: str, value: object) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A box as ((xmin, ymin, zmin), (xmax, ymax, zmax)): finite numbers, the first corner at most the second."""
    wanted = f"{owner}.{name} must be a box ((xmin, ymin, zmin), (xmax, ymax, zmax)) of finite numbers"
    if isinstance(value, (str, bytes, bool)):
        raise InvalidOptionError(f"{wanted}, got {_short(value)}")
    try:
        box = np.asarray(value)
    except ValueError:
        raise InvalidOptionError(f"{wanted}, got {_short(value)}") from None
    if box.shape != (2, 3) or box.dtype.kind not in "fiu":
        raise InvalidOptionError(f"{wanted}, got {_short(value)}")
    box = box.astype(np.float64)
    if not np.isfinite(box).all():
        raise InvalidOptionError(f"{wanted}, got {_short(value)}")
    if np.any(box[0] > box[1]):
        raise InvalidOptionError(f"{owner}.{name}'s first corner must not exceed its second on any axis, got {_short(value)}")
    return (tuple(box[0].tolist()), tuple(box[1].tolist()))  # type: ignore[return-value]


def _box_of(numbers: tuple | None) -> tuple | None:
    """A box from its six numbers on the wire (xmin, ymin, zmin, xmax, ymax, zmax); checked by the options."""
    if numbers is None:
        return None
    if len(numbers) != 6:
        raise MetadataError(f"a region must be six numbers (xmin, ymin, zmin, xmax, ymax, zmax), got {len(numbers)}")
    return (tuple(numbers[:3]), tuple(numbers[3:]))


def _check_face_indices(owner: str, faces: np.ndarray, vertex_count: int) -> None:
    smallest, largest = int(faces.min()), int(faces.max())
    if smallest < 0 or largest >= vertex_count:
        bad = int(np.flatnonzero(((faces < 0) | (faces >= vertex_count)).any(axis=1))[0])
        raise IndexRangeError(
            f"{owner}.faces must index [0, {vertex_count}) (the vertex count); face {bad} is {faces[bad].tolist()}"
        )


def _set(message: object, name: str, value: object) -> None:
    object.__setattr__(message, name, value)


def _check_registration(message: Any) -> None:
    """A request's optional `registration` (ObjectInfo's): the registration of the object it is meant for."""
    if message.registration is not None:
        _set(message, "registration", _check_int(type(message).__name__, "registration", message.registration))


def _with_registration(message: Any, metadata: dict[str, Any]) -> dict[str, Any]:
    """`metadata`, with the message's `registration` where it names one (left out otherwise, as before)."""
    if message.registration is not None:
        metadata["registration"] = message.registration
    return metadata


# --- messages ----------------------------------------------------------------------------------------


class _Message:
    KIND: ClassVar[MessageKind]
    SLOTS: ClassVar[tuple[_Slot, ...]] = ()

    def metadata(self) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> _Message:
        raise NotImplementedError

    def check_limits(self, limits: Limits) -> None:
        """Sizes carried in the metadata rather than in array headers; arrays are checked by `decode`."""


@dataclass(frozen=True)
class ObjectOptions:
    """Per-object engine options, fixed at registration.

    depth: the octree's finest level. sign: how inside is told from outside ("none" for open surfaces:
    distances are then unsigned). band: distances beyond it are clamped (None: no band). coherence: reuse
    the last frame's nearest triangles as upper bounds (off for rigid objects). refine: which cells are
    split ("surface": every cell the surface crosses; "centroid": the paper's rule). halo: finest cells of
    refinement added around those. region: a region of interest, ((xmin, ymin, zmin), (xmax, ymax, zmax)) in
    the mesh's coordinates (None: everywhere): the octree is refined only where it needs, and ADF queries
    outside it are answered exactly. bvh: the BVH's shape ("morton": linked on the device at once; "sah": made
    by the surface area heuristic on the worker's host at registration, which takes longer, for faster frames;
    "auto": sah on a CPU worker, morton on a GPU; the object's info says which). rigid: "auto" keeps the field
    for a frame that only turns and shifts the whole mesh and moves the queries into it instead (no rebuild);
    "off" rebuilds every frame.
    The engine's docstring (badf.server.adf.DistanceField) has the details.
    """

    depth: int = 7
    sign: SignMethod = "auto"
    band: float | None = None
    coherence: bool = True
    refine: RefineMethod = "surface"
    halo: int = 1
    region: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    bvh: BvhShape = "auto"
    rigid: RigidMode = "auto"

    def __post_init__(self) -> None:
        owner = "ObjectOptions"
        _set(self, "depth", _check_int(owner, "depth", self.depth, minimum=1, maximum=MAX_DEPTH))
        _check_choice(owner, "sign", self.sign, SIGN_METHODS)
        if self.band is not None:
            _set(self, "band", _check_number(owner, "band", self.band, positive=True))
        _set(self, "coherence", _check_flag(owner, "coherence", self.coherence))
        _check_choice(owner, "refine", self.refine, REFINE_METHODS)
        _set(self, "halo", _check_int(owner, "halo", self.halo, maximum=MAX_HALO))
        if self.region is not None:
            _set(self, "region", _check_box(owner, "region", self.region))
        _check_choice(owner, "bvh", self.bvh, BVH_SHAPES)
        _check_choice(owner, "rigid", self.rigid, RIGID_MODES)

    def to_json(self) -> dict[str, Any]:
        return {
            "depth": self.depth, "sign": self.sign, "band": self.band, "coherence": self.coherence,
            "refine": self.refine, "halo": self.halo,
            "region": None if self.region is None else [*self.region[0], *self.region[1]], "bvh": self.bvh,
            "rigid": self.rigid,
        }  # fmt: skip

    @classmethod
    def from_fields(cls, fields: _Fields) -> ObjectOptions:
        return cls(
            depth=fields.integer("depth"),
            sign=fields.text("sign"),  # type: ignore[arg-type]
            band=fields.number("band", optional=True),
            coherence=fields.flag("coherence"),
            refine=fields.text("refine"),  # type: ignore[arg-type]
            halo=fields.integer("halo"),
            region=_box_of(fields.items("region", (int, float), "numbers", optional=True)),
            bvh=fields.text("bvh", optional=True) or "morton",  # type: ignore[arg-type]  # absent: a client before it
            rigid=fields.text("rigid", optional=True) or "off",  # type: ignore[arg-type]  # likewise
        )


@dataclass(frozen=True, eq=False)
class RegisterRequest(_Message):
    """Create an object: its topology, initial vertices and options. `frame` numbers the initial vertices
    (a re-registration continues the old numbering); `replace` swaps out an object of the same name."""

    KIND: ClassVar[MessageKind] = MessageKind.REGISTER
    SLOTS: ClassVar[tuple[_Slot, ...]] = (
        _Slot("vertices", "float", ("N", 3), finite=True, keeps_float64=True),  # (N, 3) float32 or float64
        _Slot("faces", "index", ("M", 3)),  # (M, 3) int32, each in [0, N)
    )
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    options: ObjectOptions = field(default_factory=ObjectOptions)
    frame: int = 0
    replace: bool = False

    def __post_init__(self) -> None:
        check_name(self.name)
        if not isinstance(self.options, ObjectOptions):
            raise InvalidOptionError(f"RegisterRequest.options must be ObjectOptions, got {_short(self.options)}")
        _set(self, "frame", _check_int("RegisterRequest", "frame", self.frame))
        _set(self, "replace", _check_flag("RegisterRequest", "replace", self.replace))
        _canonical_arrays(self)
        _check_face_indices("RegisterRequest", self.faces, len(self.vertices))

    def metadata(self) -> dict[str, Any]:
        return {"name": self.name, "frame": self.frame, "replace": self.replace, "options": self.options.to_json()}

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> RegisterRequest:
        return cls(
            fields.text("name"),
            arrays["vertices"],  # type: ignore[arg-type]
            arrays["faces"],  # type: ignore[arg-type]
            options=ObjectOptions.from_fields(fields.nested("options")),
            frame=fields.integer("frame"),
            replace=fields.flag("replace"),
        )


@dataclass(frozen=True)
class ObjectInfo(_Message):
    """One object as its worker sees it. `frame` is the newest applied frame's number; `registration`
    is drawn at random for each registration and changes when the object is registered again (with
    `replace`, after a delete, or on a worker that restarted), so a watcher tells a new mesh from a new
    frame, and a handle tells its object from another of the same name; `field_info` and
    `field_stats` are the engine's own reports (resolved options, timings in ms, device bytes)."""

    KIND: ClassVar[MessageKind] = MessageKind.OBJECT_INFO
    name: str
    worker: str
    frame: int
    vertex_count: int
    face_count: int
    options: ObjectOptions
    frames_applied: int = 0
    frames_dropped: int = 0
    frames_rejected: int = 0
    queries_answered: int = 0
    points_answered: int = 0
    registration: int = 0
    last_error: str | None = None
    field_info: dict[str, Any] = field(default_factory=dict)
    field_stats: dict[str, Any] = field(default_factory=dict)

    _COUNTERS: ClassVar[tuple[str, ...]] = (
        "frame", "vertex_count", "face_count", "frames_applied", "frames_dropped",
        "frames_rejected", "queries_answered", "points_answered", "registration",
    )  # fmt: skip

    def __post_init__(self) -> None:
        check_name(self.name)
        check_name(self.worker, what="worker id")
        for name in self._COUNTERS:
            _set(self, name, _check_int("ObjectInfo", name, getattr(self, name)))

    def metadata(self) -> dict[str, Any]:
        metadata = {name: getattr(self, name) for name in self._COUNTERS}
        metadata.update(
            name=self.name,
            worker=self.worker,
            options=self.options.to_json(),
            last_error=self.last_error,
            field_info=self.field_info,
            field_stats=self.field_stats,
        )
        return metadata

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> ObjectInfo:
        return cls(
            name=fields.text("name"),
            worker=fields.text("worker"),
            options=ObjectOptions.from_fields(fields.nested("options")),
            last_error=fields.text("last_error", optional=True),
            field_info=fields.mapping("field_info"),
            field_stats=fields.mapping("field_stats"),
            **{name: fields.integer(name) for name in cls._COUNTERS},
        )


@dataclass(frozen=True, eq=False)
class Frame(_Message):
    """New vertex positions for an object, numbered by the sender; numbers must increase per object.
    `registration` (ObjectInfo's) names the registration the sender means: a frame for one that has since
    been replaced is stale, so it never lands on another mesh of the same vertex count. None: whichever."""

    KIND: ClassVar[MessageKind] = MessageKind.FRAME
    SLOTS: ClassVar[tuple[_Slot, ...]] = (_Slot("vertices", "float", ("N", 3), finite=True, keeps_float64=True),)
    name: str
    frame: int
    vertices: np.ndarray
    registration: int | None = None

    def __post_init__(self) -> None:
        check_name(self.name)
        _set(self, "frame", _check_int("Frame", "frame", self.frame))
        _check_registration(self)
        _canonical_arrays(self)

    def metadata(self) -> dict[str, Any]:
        return _with_registration(self, {"name": self.name, "frame": self.frame})

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> Frame:
        return cls(fields.text("name"), fields.integer("frame"), arrays["vertices"],  # type: ignore[arg-type]
                   registration=fields.integer("registration", optional=True))


@dataclass(frozen=True)
class FrameAck(_Message):
    """The frame that a blocking update applied."""

    KIND: ClassVar[MessageKind] = MessageKind.FRAME_ACK
    name: str
    frame: int

    def __post_init__(self) -> None:
        check_name(self.name)
        _set(self, "frame", _check_int("FrameAck", "frame", self.frame))

    def metadata(self) -> dict[str, Any]:
        return {"name": self.name, "frame": self.frame}

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> FrameAck:
        return cls(fields.text("name"), fields.integer("frame"))


@dataclass(frozen=True, eq=False)
class QueryRequest(_Message):
    """A batch of points and the outputs wanted: interpolated from the ADF ("adf") or exact ("exact").
    `registration`, as in Frame: a request for a registration since replaced is answered NOT_FOUND."""

    KIND: ClassVar[MessageKind] = MessageKind.QUERY
    SLOTS: ClassVar[tuple[_Slot, ...]] = (_Slot("points", "float", ("P", 3), finite=True, keeps_float64=True),)
    name: str
    points: np.ndarray
    mode: QueryMode = "adf"
    outputs: tuple[QueryOutput, ...] = ("distance",)
    registration: int | None = None

    def __post_init__(self) -> None:
        check_name(self.name)
        _check_registration(self)
        _check_choice("QueryRequest", "mode", self.mode, QUERY_MODES)
        if isinstance(self.outputs, str) or not self.outputs:
            raise InvalidOptionError(f"QueryRequest.outputs must be a non-empty sequence of {', '.join(QUERY_OUTPUTS)}")
        outputs = tuple(self.outputs)
        for output in outputs:
            _check_choice("QueryRequest", "outputs", output, QUERY_OUTPUTS)
        if len(set(outputs)) != len(outputs):
            raise InvalidOptionError(f"QueryRequest.outputs names an output twice: {outputs}")
        _set(self, "outputs", outputs)
        _canonical_arrays(self)

    def metadata(self) -> dict[str, Any]:
        return _with_registration(self, {"name": self.name, "mode": self.mode, "outputs": list(self.outputs)})

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> QueryRequest:
        return cls(
            fields.text("name"),
            arrays["points"],  # type: ignore[arg-type]
            mode=fields.text("mode"),  # type: ignore[arg-type]
            outputs=fields.items("outputs", (str,), "output names"),  # type: ignore[arg-type]
            registration=fields.integer("registration", optional=True),
        )


@dataclass(frozen=True, eq=False)
class QueryReply(_Message):
    """The outputs asked for, for the newest frame applied when the query ran (`frame`)."""

    KIND: ClassVar[MessageKind] = MessageKind.QUERY_REPLY
    SLOTS: ClassVar[tuple[_Slot, ...]] = (
        _Slot("distance", "float", ("P",), optional=True),  # (P,) float32, signed: negative inside
        _Slot("closest_point", "float", ("P", 3), optional=True),  # (P, 3) float32
        _Slot("normal", "float", ("P", 3), optional=True),  # (P, 3) float32, unit gradient of the distance
        _Slot("face", "index", ("P",), optional=True),  # (P,) int32, a nearest face
    )
    name: str
    frame: int
    distance: np.ndarray | None = None
    closest_point: np.ndarray | None = None
    normal: np.ndarray | None = None
    face: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_name(self.name)
        _set(self, "frame", _check_int("QueryReply", "frame", self.frame))
        _canonical_arrays(self)

    def metadata(self) -> dict[str, Any]:
        return {"name": self.name, "frame": self.frame}

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> QueryReply:
        return cls(fields.text("name"), fields.integer("frame"), **arrays)


@dataclass(frozen=True)
class SliceRequest(_Message):
    """A planar slice of the field: the plane `axis` = `position` (world units) across the object's domain,
    sampled on a `resolution` x `resolution` grid; `cells` asks for the octree cells the plane crosses (only
    those with a level in `levels` = (lowest, highest), or all when None); `corners` for corner sample
    points (not served yet: the engine has no per-plane corner list). `registration` as in QueryRequest."""

    KIND: ClassVar[MessageKind] = MessageKind.SLICE_REQUEST
    name: str
    axis: Axis
    position: float
    resolution: int = 256
    levels: tuple[int, int] | None = None
    cells: bool = True
    corners: bool = False
    registration: int | None = None

    def __post_init__(self) -> None:
        owner = "SliceRequest"
        check_name(self.name)
        _check_registration(self)
        _check_choice(owner, "axis", self.axis, AXES)
        _set(self, "position", _check_number(owner, "position", self.position))
        _set(self, "resolution", _check_int(owner, "resolution", self.resolution, minimum=1))
        if self.levels is not None:
            if isinstance(self.levels, str) or len(self.levels) != 2:
                raise InvalidOptionError(f"{owner}.levels must be (lowest, highest) or None, got {_short(self.levels)}")
            low = _check_int(owner, "levels[0]", self.levels[0], maximum=MAX_DEPTH)
            high = _check_int(owner, "levels[1]", self.levels[1], minimum=low, maximum=MAX_DEPTH)
            _set(self, "levels", (low, high))
        _set(self, "cells", _check_flag(owner, "cells", self.cells))
        _set(self, "corners", _check_flag(owner, "corners", self.corners))

    def check_limits(self, limits: Limits) -> None:
        if self.resolution > limits.max_slice_resolution:
            raise LimitExceededError(
                f"SliceRequest.resolution is {self.resolution}; the limit is {limits.max_slice_resolution}"
            )

    def metadata(self) -> dict[str, Any]:
        return _with_registration(self, {
            "name": self.name, "axis": self.axis, "position": self.position, "resolution": self.resolution,
            "levels": None if self.levels is None else list(self.levels), "cells": self.cells, "corners": self.corners,
        })  # fmt: skip

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> SliceRequest:
        return cls(
            fields.text("name"),
            fields.text("axis"),  # type: ignore[arg-type]
            fields.number("position"),  # type: ignore[arg-type]
            resolution=fields.integer("resolution"),
            levels=fields.items("levels", (int,), "integers", optional=True),  # type: ignore[arg-type]
            cells=fields.flag("cells"),
            corners=fields.flag("corners"),
            registration=fields.integer("registration", optional=True),
        )


@dataclass(frozen=True, eq=False)
class SliceReply(_Message):
    """Signed distances on the slice plane and, when asked, the octree cells it crosses.

    The plane's axes (u, v) are the two other than `axis` in x, y, z order (x: (y, z); y: (x, z); z: (x, y)).
    The grid's rows run along v and its columns along u. `extent` is ((u_min, v_min), (u_max, v_max)) in
    world units, the region the grid covers; sample (i, j) is at u = u_min + (j + 0.5) (u_max - u_min) / W,
    v likewise with i and H. Cells: world-space boxes (min corner, max corner), octree levels (0 = the
    domain cube) and flags (CELL_LEAF, CELL_EMPTY: a leaf holding no surface, interpolated from its parent).
    """

    KIND: ClassVar[MessageKind] = MessageKind.SLICE_REPLY
    SLOTS: ClassVar[tuple[_Slot, ...]] = (
        _Slot("grid", "float", ("H", "W")),  # (H, W) float32 signed distance, negative inside
        _Slot("cell_boxes", "float", ("K", 2, 3), optional=True),  # (K, 2, 3) float32: min corner, max corner
        _Slot("cell_levels", "level", ("K",), optional=True),  # (K,) uint8 octree level of each cell
        _Slot("cell_flags", "level", ("K",), optional=True),  # (K,) uint8: CELL_LEAF | CELL_EMPTY bits
        _Slot("corner_points", "float", ("C", 3), optional=True),  # (C, 3) float32 corner sample points
    )
    name: str
    frame: int
    axis: Axis
    position: float
    extent: tuple[tuple[float, float], tuple[float, float]]
    grid: np.ndarray
    cell_boxes: np.ndarray | None = None
    cell_levels: np.ndarray | None = None
    cell_flags: np.ndarray | None = None
    corner_points: np.ndarray | None = None

    def __post_init__(self) -> None:
        owner = "SliceReply"
        check_name(self.name)
        _set(self, "frame", _check_int(owner, "frame", self.frame))
        _check_choice(owner, "axis", self.axis, AXES)
        _set(self, "position", _check_number(owner, "position", self.position))
        try:
            (u0, v0), (u1, v1) = self.extent
        except (TypeError, ValueError):
            raise InvalidOptionError(
                f"{owner}.extent must be ((u_min, v_min), (u_max, v_max)), got {_short(self.extent)}"
            ) from None
        low = (_check_number(owner, "extent", u0), _check_number(owner, "extent", v0))
        high = (_check_number(owner, "extent", u1), _check_number(owner, "extent", v1))
        _set(self, "extent", (low, high))
        if len({self.cell_boxes is None, self.cell_levels is None, self.cell_flags is None}) > 1:
            raise ShapeError(f"{owner}: cell_boxes, cell_levels and cell_flags come together or not at all")
        _canonical_arrays(self)

    def metadata(self) -> dict[str, Any]:
        return {
            "name": self.name, "frame": self.frame, "axis": self.axis, "position": self.position,
            "extent": [list(self.extent[0]), list(self.extent[1])],
        }  # fmt: skip

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> SliceReply:
        extent = fields.items("extent", (list,), "two [u, v] pairs")
        return cls(
            fields.text("name"),
            fields.integer("frame"),
            fields.text("axis"),  # type: ignore[arg-type]
            fields.number("position"),  # type: ignore[arg-type]
            extent,  # type: ignore[arg-type]
            **arrays,  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class MeshRequest(_Message):
    """Ask for an object's newest applied vertices and, with `faces`, its faces (which never change: a viewer
    that already has them asks with faces=False). `registration` as in QueryRequest."""

    KIND: ClassVar[MessageKind] = MessageKind.MESH_REQUEST
    name: str
    faces: bool = True
    registration: int | None = None

    def __post_init__(self) -> None:
        check_name(self.name)
        _check_registration(self)
        _set(self, "faces", _check_flag("MeshRequest", "faces", self.faces))

    def metadata(self) -> dict[str, Any]:
        return _with_registration(self, {"name": self.name, "faces": self.faces})

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> MeshRequest:
        return cls(fields.text("name"), faces=fields.flag("faces"),
                   registration=fields.integer("registration", optional=True))


@dataclass(frozen=True, eq=False)
class MeshReply(_Message):
    """The vertices of the newest applied frame (`frame`), and the faces when they were asked for."""

    KIND: ClassVar[MessageKind] = MessageKind.MESH_REPLY
    SLOTS: ClassVar[tuple[_Slot, ...]] = (
        _Slot("vertices", "float", ("N", 3), finite=True, keeps_float64=True),  # (N, 3) float32 or float64
        _Slot("faces", "index", ("M", 3), optional=True),  # (M, 3) int32, each in [0, N)
    )
    name: str
    frame: int
    vertices: np.ndarray
    faces: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_name(self.name)
        _set(self, "frame", _check_int("MeshReply", "frame", self.frame))
        _canonical_arrays(self)
        if self.faces is not None:
            _check_face_indices("MeshReply", self.faces, len(self.vertices))

    def metadata(self) -> dict[str, Any]:
        return {"name": self.name, "frame": self.frame}

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> MeshReply:
        return cls(fields.text("name"), fields.integer("frame"), **arrays)  # type: ignore[arg-type]


@dataclass(frozen=True)
class InfoRequest(_Message):
    """Ask for an object's info (`name`), or, on a wildcard or worker key, for every match (None).
    `registration` as in QueryRequest (with a name only)."""

    KIND: ClassVar[MessageKind] = MessageKind.INFO_REQUEST
    name: str | None = None
    registration: int | None = None

    def __post_init__(self) -> None:
        if self.name is not None:
            check_name(self.name)
        elif self.registration is not None:
            raise InvalidOptionError("InfoRequest.registration needs a name: it names one object's registration")
        _check_registration(self)

    def metadata(self) -> dict[str, Any]:
        return _with_registration(self, {"name": self.name})

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> InfoRequest:
        return cls(fields.text("name", optional=True), registration=fields.integer("registration", optional=True))


@dataclass(frozen=True)
class WorkerInfo(_Message):
    """A worker: its id, device, the limits it enforces, and its load: what it holds (objects, vertices,
    faces), what waits (requests queued for its objects, registrations not yet built), and what it has done
    since it started (frames applied, queries and points answered; difference two reports for rates)."""

    KIND: ClassVar[MessageKind] = MessageKind.WORKER_INFO
    worker: str
    device: str
    object_count: int
    vertex_count: int
    face_count: int
    uptime_s: float
    limits: dict[str, int] = field(default_factory=dict)
    requests_waiting: int = 0
    frames_applied: int = 0
    queries_answered: int = 0
    points_answered: int = 0

    _COUNTS: ClassVar[tuple[str, ...]] = (
        "object_count", "vertex_count", "face_count",
        "requests_waiting", "frames_applied", "queries_answered", "points_answered",
    )  # fmt: skip

    def __post_init__(self) -> None:
        check_name(self.worker, what="worker id")
        for name in self._COUNTS:
            _set(self, name, _check_int("WorkerInfo", name, getattr(self, name)))
        _set(self, "uptime_s", _check_number("WorkerInfo", "uptime_s", self.uptime_s))

    def metadata(self) -> dict[str, Any]:
        return {
            "worker": self.worker, "device": self.device, "uptime_s": self.uptime_s, "limits": self.limits,
            **{name: getattr(self, name) for name in self._COUNTS},
        }  # fmt: skip

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> WorkerInfo:
        return cls(
            fields.text("worker"),
            fields.text("device"),
            fields.integer("object_count"),
            fields.integer("vertex_count"),
            fields.integer("face_count"),
            fields.number("uptime_s"),  # type: ignore[arg-type]
            fields.mapping("limits"),
            requests_waiting=fields.integer("requests_waiting"),
            frames_applied=fields.integer("frames_applied"),
            queries_answered=fields.integer("queries_answered"),
            points_answered=fields.integer("points_answered"),
        )


@dataclass(frozen=True)
class DeleteRequest(_Message):
    """Delete an object; `registration` as in QueryRequest (a handle's delete never removes the object another
    client registered in its place)."""

    KIND: ClassVar[MessageKind] = MessageKind.DELETE_REQUEST
    name: str
    registration: int | None = None

    def __post_init__(self) -> None:
        check_name(self.name)
        _check_registration(self)

    def metadata(self) -> dict[str, Any]:
        return _with_registration(self, {"name": self.name})

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> DeleteRequest:
        return cls(fields.text("name"), registration=fields.integer("registration", optional=True))


@dataclass(frozen=True)
class Deleted(_Message):
    """An object is gone; `frame` was its last applied frame."""

    KIND: ClassVar[MessageKind] = MessageKind.DELETED
    name: str
    frame: int

    def __post_init__(self) -> None:
        check_name(self.name)
        _set(self, "frame", _check_int("Deleted", "frame", self.frame))

    def metadata(self) -> dict[str, Any]:
        return {"name": self.name, "frame": self.frame}

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> Deleted:
        return cls(fields.text("name"), fields.integer("frame"))


@dataclass(frozen=True)
class ErrorReply(_Message):
    """Why a request failed: an `ErrorCode` value (kept as int, so codes from newer workers still decode)
    and a message saying what was expected and what came."""

    KIND: ClassVar[MessageKind] = MessageKind.ERROR
    code: int
    message: str

    def __post_init__(self) -> None:
        _set(self, "code", _check_int("ErrorReply", "code", self.code, maximum=65535))
        if not isinstance(self.message, str):
            raise InvalidOptionError(f"ErrorReply.message must be a string, got {_short(self.message)}")
        if len(self.message) > MAX_ERROR_MESSAGE_LENGTH:
            _set(self, "message", self.message[: MAX_ERROR_MESSAGE_LENGTH - 3] + "...")

    def metadata(self) -> dict[str, Any]:
        return {"code": self.code, "message": self.message}

    @classmethod
    def from_parts(cls, fields: _Fields, arrays: dict[str, np.ndarray | None]) -> ErrorReply:
        return cls(fields.integer("code"), fields.text("message"))


Message = (
    RegisterRequest | ObjectInfo | Frame | FrameAck | QueryRequest | QueryReply | SliceRequest | SliceReply
    | InfoRequest | WorkerInfo | DeleteRequest | Deleted | ErrorReply | MeshRequest | MeshReply
)  # fmt: skip
MESSAGE_TYPES: tuple[type[_Message], ...] = (
    RegisterRequest, ObjectInfo, Frame, FrameAck, QueryRequest, QueryReply, SliceRequest, SliceReply,
    InfoRequest, WorkerInfo, DeleteRequest, Deleted, ErrorReply, MeshRequest, MeshReply,
)  # fmt: skip
_TYPES_BY_KIND: dict[int, type[_Message]] = {cls.KIND: cls for cls in MESSAGE_TYPES}
M = TypeVar("M", bound=_Message)


def encode(message: Message) -> bytearray:
    """The message's bytes, ready for a Zenoh payload."""
    return pack(message.KIND, message.metadata(), [getattr(message, slot.name) for slot in message.SLOTS])


def check_sizes(message: Message, limits: Limits) -> None:
    """LimitExceededError where `message` carries more than `limits` allow, as its receiver would say: a
    sender can tell before the bytes go (a 50 MB query one point over the limit went out to be refused)."""
    shapes = [None if getattr(message, slot.name) is None else np.shape(getattr(message, slot.name))
              for slot in message.SLOTS]  # fmt: skip
    _check_shapes(type(message).__name__, message.SLOTS, shapes, limits)
    message.check_limits(limits)


def decode(data: bytes | bytearray, expect: type[M], *, limits: Limits = DEFAULT_LIMITS) -> M:
    """The message of type `expect` in `data`; raises a MessageError subclass saying what is wrong."""
    owner = expect.__name__

    def inspect(kind: int, descriptors: tuple[Descriptor, ...]) -> None:
        cls = _TYPES_BY_KIND.get(kind)
        if cls is None:
            raise WrongKindError(f"unknown message kind {kind}; expected {owner} ({int(expect.KIND)})")
        if cls is not expect:
            raise WrongKindError(f"expected {owner}, got {cls.__name__}")
        if len(descriptors) != len(expect.SLOTS):
            raise MalformedMessageError(
                f"{owner} carries {len(expect.SLOTS)} array slots; this one has {len(descriptors)}"
            )
        for slot, descriptor in zip(expect.SLOTS, descriptors):
            if descriptor.shape is not None and descriptor.dtype not in _WIRE_ACCEPTS[slot.element]:
                accepted = " or ".join(str(NUMPY_DTYPES[code]) for code in _WIRE_ACCEPTS[slot.element])
                raise DtypeError(
                    f"{owner}.{slot.name} must be {accepted} on the wire, got {NUMPY_DTYPES[descriptor.dtype]}"
                )
        _check_shapes(owner, expect.SLOTS, [descriptor.shape for descriptor in descriptors], limits)

    raw = unpack(data, limits, inspect)
    arrays = {slot.name: array for slot, array in zip(expect.SLOTS, raw.arrays)}
    message = expect.from_parts(_Fields(owner, raw.metadata), arrays)
    message.check_limits(limits)
    return message  # type: ignore[return-value]
