"""Reading a mesh, or a recorded sequence of its frames, from a file named on the command line.

One reader for `badf demo` and every benchmark: an .npz with `vertices` (N, 3) or frames (T, N, 3) and
`faces` (M, 3), or any mesh file trimesh reads (.obj, .ply, .stl, .off, .glb, ...). A file that cannot be
read, holds no triangles, has face indices out of range or vertices that are NaN or Inf, or that the
engine would refuse (coordinates past its range, a first frame of zero extent), is a `MeshFileError`
naming the file and what was wrong; the command line prints it as one line. So is an .npz whose arrays
declare more bytes than half the machine's memory (read before anything is unpacked), and an OBJ face
index 0 (they count from 1). Relative (negative) OBJ indices, which trimesh reads against the file's last
vertex, are made absolute first.
"""

from __future__ import annotations

import io
import os
import pathlib
import re
import zipfile

import numpy as np


MESH_HELP = "a mesh file: .npz with vertices (N, 3) or frames (T, N, 3) and faces (M, 3), or any file trimesh reads"


class MeshFileError(ValueError):
    """A mesh file that does not exist, cannot be read, or does not hold a triangle mesh."""


def read_frames(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(frames (T, N, 3), float64 where the file's are, else float32; faces int32 (M, 3)); a single mesh is one
    frame."""
    if not os.fspath(path):
        raise MeshFileError("an empty name where a mesh file was expected")
    path = pathlib.Path(path)
    if not path.exists():
        raise MeshFileError(f"{path}: no such file")
    if not path.is_file():
        raise MeshFileError(f"{path}: not a file")
    if path.suffix.lower() == ".npz":
        vertices, faces = _read_npz(path)
    else:
        vertices, faces = _read_with_trimesh(path)
    frames = vertices[None] if vertices.ndim == 2 else vertices
    if frames.ndim != 3 or frames.shape[2] != 3 or frames.shape[0] == 0 or frames.shape[1] == 0:
        raise MeshFileError(f"{path}: vertices of shape {vertices.shape}, expected (N, 3) or frames (T, N, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise MeshFileError(f"{path}: faces of shape {faces.shape}, expected (M, 3) with M > 0")
    if not np.issubdtype(faces.dtype, np.integer):
        raise MeshFileError(f"{path}: faces of dtype {faces.dtype}, expected integers")
    if faces.min() < 0 or faces.max() >= frames.shape[1]:
        raise MeshFileError(f"{path}: face indices span {faces.min()}..{faces.max()}, but there are "
                            f"{frames.shape[1]} vertices")
    if not np.issubdtype(frames.dtype, np.number) or np.issubdtype(frames.dtype, np.complexfloating):
        raise MeshFileError(f"{path}: vertices of dtype {frames.dtype}, expected real numbers")
    # float64 files stay float64 (far from the origin float32 would weld a mesh's vertices: a unit sphere 1e7 out
    # kept 26 of its 642), and every other type becomes float32, which the engine computes in
    precision = np.float64 if frames.dtype == np.float64 else np.float32
    with np.errstate(over="ignore"):  # values past float32's range become inf, and are told below
        frames = np.ascontiguousarray(frames, precision)
    finite = np.isfinite(frames).all(axis=2)
    if not finite.all():
        frame, vertex = np.argwhere(~finite)[0]
        where = f"vertex {vertex}" + (f" of frame {frame}" if frames.shape[0] > 1 else "")
        raise MeshFileError(f"{path}: {where} is {frames[frame, vertex].tolist()} ({(~finite).sum()} vertices "
                            f"are NaN, Inf or beyond float32's range)")
    _check_engine_takes(path, frames, faces)
    return frames, np.ascontiguousarray(faces, np.int32)


def _check_engine_takes(path: pathlib.Path, frames: np.ndarray, faces: np.ndarray) -> None:
    """What the engine would refuse at registration, told now with the file's name (a demo started its
    worker, then failed naming no file)."""
    from badf.server.adf._inputs import MAX_COORDINATE, MIN_EXTENT

    largest = float(np.abs(frames).max())
    if largest > MAX_COORDINATE:
        raise MeshFileError(f"{path}: a coordinate of {largest:g}; the engine takes coordinates within "
                            f"+-{MAX_COORDINATE:g}")
    used = frames[:, np.unique(faces)]
    # each frame's largest side, in the frames' own precision (no float64 copy of a long sequence), compared in float64
    extents = np.max((used.max(axis=1) - used.min(axis=1)).astype(np.float64), axis=1)
    if extents[0] == 0.0:
        raise MeshFileError(f"{path}: the vertices its faces use all coincide (the mesh has zero extent)")
    # a later frame collapsed to a point is taken (the field keeps its cube), one merely tiny is not
    tiny = np.flatnonzero((extents > 0.0) & (extents < MIN_EXTENT))
    if len(tiny):
        where = f" in frame {tiny[0]}" if frames.shape[0] > 1 else ""
        raise MeshFileError(f"{path}: the mesh's extent{where} is {extents[tiny[0]]:.3g}; the engine refuses meshes "
                            f"smaller than {MIN_EXTENT:g} (scale it up)")


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3), float64 where the file's are, else float32; faces int32 (M, 3)); the first frame of a
    sequence."""
    frames, faces = read_frames(path)
    return frames[0], faces


def _read_npz(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    if not zipfile.is_zipfile(path):
        raise MeshFileError(f"{path}: not an .npz archive (numpy.savez writes one)")
    _check_declared_sizes(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [key for key in ("vertices", "faces") if key not in data.files]
            if missing:
                raise MeshFileError(f"{path}: no {' or '.join(missing)} array (it holds {', '.join(data.files) or 'none'})")
            return np.asarray(data["vertices"]), np.asarray(data["faces"])
    except MeshFileError:
        raise
    except Exception as error:  # a damaged or foreign file: zipfile, pickle and format errors alike
        raise MeshFileError(f"{path}: not a readable .npz ({type(error).__name__}: {error})") from None


def _memory_available() -> int | None:
    """Bytes of memory this machine could give a process now (MemAvailable), else half its memory, else None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return None


def _check_declared_sizes(path: pathlib.Path) -> None:
    """Refuse an .npz whose arrays declare, in their headers, more bytes than this machine has available: a few
    megabytes of zeros compressed can declare gigabytes, which np.load would allocate and fill before any check
    (4.7 GB of memory and 20 s for one of 4.7 MB, outside check, 2026-12-07)."""
    available = _memory_available()
    if available is None:
        return
    declared, arrays = 0, []
    try:
        with zipfile.ZipFile(path) as archive:
            for member in archive.infolist():
                if not member.filename.endswith(".npy"):
                    continue
                with archive.open(member) as f:
                    version = np.lib.format.read_magic(f)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read_header(f)
                declared += int(np.prod(shape, dtype=object)) * dtype.itemsize
                arrays.append(f"{member.filename[:-4]} {shape} of {dtype}")
    except Exception:  # a damaged or foreign member: np.load below names what is wrong with it
        return
    if declared > available:
        raise MeshFileError(f"{path}: its arrays ({', '.join(arrays)}) declare {declared / 2**30:.1f} GiB, more than "
                            f"the {available / 2**30:.1f} GiB this machine has available")


# an OBJ face line's indices: v, v/vt, v//vn or v/vt/vn, each a whole number, negative ones relative
_OBJ_ODD_INDEX = re.compile(rb"^[ \t]*f[ \t][^\n]*?(?:(?<=[\s/])-\d|(?<=[\s/])0+(?=[\s/]|$))", re.M)
_OBJ_KINDS = {b"v": 0, b"vt": 1, b"vn": 2}


def _obj_with_absolute_indices(path: pathlib.Path, text: bytes) -> bytes:
    """The OBJ's text with relative (negative) face indices written as absolute ones, counted from the vertices,
    texture and normal vertices before each face (trimesh reads them against the file's last vertex); a face index 0
    is a MeshFileError, as OBJ counts from 1."""
    counts = [0, 0, 0]
    lines = text.split(b"\n")
    for number, line in enumerate(lines):
        words = line.split()
        if not words:
            continue
        kind = _OBJ_KINDS.get(words[0])
        if kind is not None:
            counts[kind] += 1
            continue
        if words[0] != b"f":
            continue
        corners = []
        for word in words[1:]:
            parts = word.split(b"/")
            for k, part in enumerate(parts[:3]):
                if not part:
                    continue
                try:
                    index = int(part)
                except ValueError:
                    raise MeshFileError(f"{path}: line {number + 1}: face index {part.decode(errors='replace')!r} "
                                        "is not a whole number") from None
                if index == 0:
                    raise MeshFileError(f"{path}: line {number + 1}: face index 0 (OBJ indices count from 1)")
                if index < 0:
                    if counts[k] + index < 0:
                        raise MeshFileError(f"{path}: line {number + 1}: relative face index {index}, but only "
                                            f"{counts[k]} {('vertices', 'texture vertices', 'normals')[k]} come "
                                            "before it")
                    parts[k] = str(counts[k] + index + 1).encode()
            corners.append(b"/".join(parts))
        lines[number] = b"f " + b" ".join(corners)
    return b"\n".join(lines)


def _read_with_trimesh(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    source, kind = str(path), None
    if path.suffix.lower() == ".obj":
        text = path.read_bytes()
        if _OBJ_ODD_INDEX.search(text):  # most files have none, and skip the pass over every line
            source, kind = io.BytesIO(_obj_with_absolute_indices(path, text)), "obj"
    try:
        loaded = trimesh.load(source, file_type=kind, force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds for files it cannot parse
        raise MeshFileError(f"{path}: trimesh cannot read it ({type(error).__name__}: {error})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshFileError(f"{path}: holds no triangles")
    vertices, faces = np.asarray(loaded.vertices), np.asarray(loaded.faces)
    if path.suffix.lower() == ".stl":
        vertices, faces = _shared_corners(vertices, faces)
    return vertices, faces


def _shared_corners(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An STL file gives each triangle corners of its own. Corners at the same position become one vertex (in the
    order they first come), as the surface meant: an open surface's rim is then its holes' edges, which the winding
    numbers' correction near 1/2 can close, not every triangle's three (docs/engine.md, "Fast winding numbers")."""
    from badf.server.adf._sign import weld  # the engine's own weld, so its analysis finds nothing more to join

    welded, count = weld(vertices)
    first = np.full(count, len(vertices), dtype=np.int64)
    np.minimum.at(first, welded, np.arange(len(vertices)))
    order = np.argsort(first, kind="stable")
    rank = np.empty(count, dtype=np.int64)
    rank[order] = np.arange(count)
    return vertices[first[order]], rank[welded][faces]
