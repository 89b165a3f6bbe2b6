"""Reading a mesh, or a recorded sequence of its frames, from a file named on the command line.

One reader for `badf demo` and every benchmark: an .npz with `vertices` (N, 3) or frames (T, N, 3) and
`faces` (M, 3), or any mesh file trimesh reads (.obj, .ply, .stl, .off, .glb, ...). A file that cannot be
read, holds no triangles, has face indices out of range or vertices that are NaN or Inf, or that the
engine would refuse (coordinates past its range, a first frame of zero extent), is a `MeshFileError`
naming the file and what was wrong; the command line prints it as one line.
"""

from __future__ import annotations

import os
import pathlib
import zipfile

import numpy as np


MESH_HELP = "a mesh file: .npz with vertices (N, 3) or frames (T, N, 3) and faces (M, 3), or any file trimesh reads"


class MeshFileError(ValueError):
    """A mesh file that does not exist, cannot be read, or does not hold a triangle mesh."""


def read_frames(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(frames (T, N, 3), float64 where the file's are, else float32; faces int32 (M, 3)); a single mesh is one
    frame."""
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


def _read_with_trimesh(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds for files it cannot parse
        raise MeshFileError(f"{path}: trimesh cannot read it ({type(error).__name__}: {error})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshFileError(f"{path}: holds no triangles")
    return np.asarray(loaded.vertices), np.asarray(loaded.faces)
