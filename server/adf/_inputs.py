"""Checks at the engine's boundary: each says what was expected and what came, before any state changes."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from badf.server.adf._tolerances import MAX_DEPTH, MAX_FACES, MAX_HALO, MAX_VERTICES

# Coordinates beyond this magnitude would overflow float32 when squared inside the distance kernels.
MAX_COORDINATE = 1.0e18
# Meshes smaller than this are refused: answers are float32 in world units, subnormal below 1.2e-38 and
# spaced 1.4e-45 apart, which is 1e-5 of a size of 1.4e-40 (thirteenth outside check: at size 1e-45 exact
# distances were off by 0.2 of the diagonal, and at 1e-60 every one was 0.0).
MIN_EXTENT = 1.0e-40

QUERY_MODES: tuple[str, ...] = ("adf", "exact")
QUERY_OUTPUTS: tuple[str, ...] = ("distance", "closest_point", "normal", "face")
REFINEMENTS: tuple[str, ...] = ("surface", "centroid")
BVH_SHAPES: tuple[str, ...] = ("auto", "morton", "sah")


class InvalidInputError(ValueError):
    """Input the engine cannot use; the message says what was expected and what came."""


def _numeric_array(value, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError, OverflowError) as error:
        raise InvalidInputError(f"{name} must be an array of numbers: {error}") from None
    big = _python_int_past_64_bits(arr)
    if big is not None:  # numpy keeps such ints as objects: name the value, not only "dtype object"
        told = "an index" if name == "faces" else "a coordinate"
        raise InvalidInputError(f"{name}: {told} past 64-bit integers (one of {abs(big).bit_length()} bits)")
    if arr.dtype.kind not in "fiu":
        kinds = "integers" if name == "faces" else "numbers (float or int)"
        raise InvalidInputError(f"{name} must hold {kinds}, got dtype {arr.dtype}")
    return arr


def _python_int_past_64_bits(arr: np.ndarray) -> int | None:
    """The largest Python int of an object array of Python numbers, where it passes 64 bits; else None."""
    if arr.dtype.kind != "O" or arr.size == 0 or not all(type(x) in (int, float) for x in arr.flat):
        return None
    big = max((x for x in arr.flat if type(x) is int), key=abs, default=0)
    return big if abs(big) >= 2**63 else None


def _check_finite(arr: np.ndarray, name: str) -> None:
    """Finite and within +-MAX_COORDINATE; one min/max pass (a NaN fails both comparisons), details on failure."""
    if arr.dtype.kind != "f" or arr.size == 0:
        return
    low, high = arr.min(), arr.max()
    if low >= -MAX_COORDINATE and high <= MAX_COORDINATE:
        return
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = np.flatnonzero(bad.any(axis=-1))
        raise InvalidInputError(
            f"{name} must be finite, got {int(bad.sum())} NaN or Inf values in {len(rows)} rows (first at row {rows[0]})"
        )
    big = np.abs(arr).max()
    told = f"{float(big):g}" if np.isfinite(float(big)) else np.format_float_scientific(big, precision=4)  # long double
    raise InvalidInputError(f"{name} must lie within +-{MAX_COORDINATE:g}, got a coordinate of {told}")


def as_points(value, name: str = "points", *, expected_count: int | None = None, allow_empty: bool = True) -> np.ndarray:
    """A (P, 3) float array of finite coordinates (float64 stays float64 for exact recentring; ints become float64)."""
    arr = _numeric_array(value, name)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"{name} must have shape (count, 3), got {arr.shape}")
    if expected_count is not None and arr.shape[0] != expected_count:
        raise InvalidInputError(
            f"{name} must have {expected_count} rows (the registered vertex count), got {arr.shape[0]}"
        )
    if not allow_empty and arr.shape[0] == 0:
        raise InvalidInputError(f"{name} must not be empty")
    if arr.dtype.kind == "f" and arr.dtype.itemsize > 8:
        _check_finite(arr, name)  # before float64, which would make 1e400 an Inf and tell it as one
    if arr.dtype.kind != "f" or arr.dtype.itemsize > 8:
        arr = arr.astype(np.float64)
    elif arr.dtype.itemsize < 4:
        arr = arr.astype(np.float32)
    _check_finite(arr, name)
    return np.ascontiguousarray(arr)


def as_vertices(value, *, expected_count: int | None = None) -> np.ndarray:
    arr = as_points(value, "vertices", expected_count=expected_count, allow_empty=False)
    if arr.shape[0] > MAX_VERTICES:
        raise InvalidInputError(f"vertices: at most {MAX_VERTICES} supported, got {arr.shape[0]}")
    return arr


def as_faces(value, vertex_count: int) -> np.ndarray:
    """A (M, 3) int32 array of vertex indices in [0, vertex_count)."""
    arr = _numeric_array(value, "faces")
    if arr.dtype.kind not in "iu":
        raise InvalidInputError(f"faces must hold integer vertex indices, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"faces must have shape (count, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise InvalidInputError("faces must not be empty: a distance field needs at least one triangle")
    if arr.shape[0] > MAX_FACES:
        raise InvalidInputError(f"faces: at most {MAX_FACES} supported, got {arr.shape[0]}")
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi >= vertex_count:
        bad = np.flatnonzero(((arr < 0) | (arr >= vertex_count)).any(axis=1))
        raise InvalidInputError(
            f"faces must index vertices 0..{vertex_count - 1}, got indices in [{lo}, {hi}] "
            f"({len(bad)} faces out of range, first at row {bad[0]})"
        )
    return np.ascontiguousarray(arr, dtype=np.int32)


def check_depth(depth) -> int:
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)):
        raise InvalidInputError(f"depth must be an integer in 1..{MAX_DEPTH}, got {_shown(depth)}")
    if not 1 <= int(depth) <= MAX_DEPTH:
        raise InvalidInputError(f"depth must be in 1..{MAX_DEPTH}, got {_shown(int(depth))}")
    return int(depth)


def check_halo(halo) -> int:
    if isinstance(halo, bool) or not isinstance(halo, (int, np.integer)) or not 0 <= int(halo) <= MAX_HALO:
        raise InvalidInputError(f"halo must be an integer in 0..{MAX_HALO}, got {_shown(halo)}")
    return int(halo)


def check_band(band) -> float | None:
    if band is None:
        return None
    if isinstance(band, (bool, np.bool_, str, bytes)):
        raise InvalidInputError(f"band must be a positive number or None, got {_shown(band)}")
    try:
        value = float(band)
    except (TypeError, ValueError):
        raise InvalidInputError(f"band must be a positive number or None, got {_shown(band)}") from None
    except OverflowError:  # an int past float's range
        value = float("inf")
    if not np.isfinite(value) or value <= 0.0:
        raise InvalidInputError(f"band must be a positive finite number or None, got {_shown(band)}")
    return value


_SHOWN_LENGTH = 100


def _shown(value) -> str:
    """A value as an error message shows it: its repr, cut in the middle where it is long (an int of 400 digits,
    a string of thousands of characters), so that the message stays a line. The protocol's checks cut theirs the
    same way (badf.protocol._messages._short), which this layer does not import."""
    text = repr(value)
    return text if len(text) <= _SHOWN_LENGTH else f"{text[:60]}...{text[-20:]}"


def check_region(region) -> np.ndarray | None:
    """None, or a box as a (2, 3) float64 array: its lowest corner, then its highest, each at least the other
    on every axis (a flat box, one thick at no axis, is allowed: it still meets a layer of cells)."""
    if region is None:
        return None
    if isinstance(region, (bool, str, bytes)):
        raise InvalidInputError(f"region must be None or a box [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {_shown(region)}")
    arr = _numeric_array(region, "region")
    if arr.shape != (2, 3):
        raise InvalidInputError(f"region must have shape (2, 3) (its lowest corner, then its highest), got {arr.shape}")
    _check_finite(arr, "region")  # before float64, which would make a long double's 1e4000 an Inf and tell it so
    arr = arr.astype(np.float64)
    reversed_axes = np.flatnonzero(arr[0] > arr[1])
    if len(reversed_axes):
        k = int(reversed_axes[0])
        raise InvalidInputError(f"region's lowest corner must not exceed its highest: on {'xyz'[k]} it runs from "
                                f"{arr[0, k]:g} to {arr[1, k]:g}")
    return arr


def check_choice(value, name: str, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise InvalidInputError(f"{name} must be one of {', '.join(choices)}; got {_shown(value)}")
    return value


def check_outputs(outputs) -> tuple[str, ...]:
    if isinstance(outputs, str):
        outputs = (outputs,)
    if isinstance(outputs, (bytes, bytearray)) or not isinstance(outputs, Iterable):  # bytes iterate as integers
        raise InvalidInputError(f"outputs must be a sequence of names from {QUERY_OUTPUTS}, got {_shown(outputs)}")
    names = tuple(outputs)
    if not names:
        raise InvalidInputError(f"outputs must name at least one of {', '.join(QUERY_OUTPUTS)}")
    unknown = [name for name in names if name not in QUERY_OUTPUTS]
    if unknown:
        raise InvalidInputError(f"unknown outputs {_shown(unknown)}; expected names from {', '.join(QUERY_OUTPUTS)}")
    return tuple(dict.fromkeys(names))


def check_flag(value, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidInputError(f"{name} must be True or False, got {_shown(value)}")
    return bool(value)


def check_axis(axis) -> int:
    if isinstance(axis, str) and axis in ("x", "y", "z"):
        return "xyz".index(axis)
    if _is_whole(axis) and 0 <= int(axis) <= 2:
        return int(axis)
    raise InvalidInputError(f"axis must be 'x', 'y' or 'z' (or 0, 1, 2), got {_shown(axis)}")


def check_finite_number(value, name: str) -> float:
    if isinstance(value, (str, bytes, bool, np.bool_)):  # float("0.5") and float(True) would pass
        raise InvalidInputError(f"{name} must be a number, got {_shown(value)}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a number, got {_shown(value)}") from None
    except OverflowError:  # an int past float's range
        number = float("inf")
    if not np.isfinite(number):
        raise InvalidInputError(f"{name} must be finite, got {_shown(value)}")
    return number


def check_resolution(resolution, limit: int = 2048) -> tuple[int, int]:
    """(rows, cols) from an int (square) or a (cols, rows) pair, each 1..limit."""
    pair = (resolution, resolution) if _is_whole(resolution) else resolution
    if not (isinstance(pair, (tuple, list, np.ndarray)) and len(pair) == 2 and all(_is_whole(x) for x in pair)):
        raise InvalidInputError(f"resolution must be an int or (cols, rows) of ints, got {_shown(resolution)}")
    cols, rows = (int(x) for x in pair)
    if not (1 <= cols <= limit and 1 <= rows <= limit):
        raise InvalidInputError(f"resolution must be 1..{limit} per side, got {_shown(resolution)}")
    return rows, cols


def _is_whole(value) -> bool:
    """An integer, not a bool (True is an int to Python) and not a float that int() would truncate."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_level(level, depth: int) -> int:
    if not _is_whole(level) or not 0 <= int(level) <= depth:
        raise InvalidInputError(f"max_level must be an integer in 0..{depth}, got {_shown(level)}")
    return int(level)
