"""Test meshes: the bundled and shared data sets, and generated shapes with known properties."""

from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
import trimesh

ROOT = pathlib.Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "tests" / "data"
# the shared data folder beside the checkout; BADF_SHARED_DATA points elsewhere (e.g. on a GPU machine)
SHARED = pathlib.Path(os.environ.get("BADF_SHARED_DATA", ROOT.parent / "shared" / "data"))


def data_file(name: str) -> pathlib.Path:
    for folder in (BUNDLED, SHARED):
        path = folder / f"{name}.npz"
        if path.exists():
            return path
    pytest.skip(f"{name}.npz is in neither {BUNDLED} nor {SHARED}")


def load(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float32 (N, 3), faces int32 (M, 3)); for a sequence, its first frame."""
    if name in GENERATED:
        return GENERATED[name]()
    data = np.load(data_file(name))
    vertices = data["vertices"]
    if vertices.ndim == 3:
        vertices = vertices[0]
    return np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(data["faces"], np.int32)


def load_sequence(name: str) -> tuple[np.ndarray, np.ndarray]:
    data = np.load(data_file(name))
    return data["vertices"].astype(np.float32), data["faces"].astype(np.int32)


def _mesh(m: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)


def sphere():
    return _mesh(trimesh.creation.icosphere(subdivisions=3, radius=1.0))


def box():
    return _mesh(trimesh.creation.box(extents=(2.0, 1.0, 0.5)))


def torus():
    return _mesh(trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=48, minor_sections=16))


def wire(radius: float = 1e-3, height: float = 1.0, sections: int = 8):
    """A closed cylinder far thinner than it is long: a feature thinner than any cell."""
    return _mesh(trimesh.creation.cylinder(radius=radius, height=height, sections=sections))


def sheet(n: int = 24):
    """An open square sheet (like cloth), n x n quads in the z = 0 plane, slightly waved."""
    x, y = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(-1, 1, n + 1), indexing="ij")
    z = 0.1 * np.sin(2.0 * x) * np.cos(1.5 * y)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3).astype(np.float32)
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return vertices, faces


def single_triangle():
    return np.array([[0, 0, 0], [1, 0, 0], [0.2, 0.9, 0.1]], np.float32), np.array([[0, 1, 2]], np.int32)


GENERATED = {"sphere": sphere, "box": box, "torus": torus, "sheet": sheet, "single-triangle": single_triangle}

# Meshes and whether they are closed (the oracle's sign is meaningful everywhere only for closed ones).
def cone_on_cube(lift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A unit cube and a closed cone standing on its tip on the cube's corner (1, 1, 1), raised by `lift`
    along (1, 1, 1): with lift 0 the two parts touch at that one point (a vertex of each)."""
    cube = trimesh.creation.box(bounds=[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    cone = trimesh.creation.cone(radius=0.4, height=0.5, sections=24)
    tip_down = np.asarray(cone.vertices) * [1.0, 1.0, -1.0]
    cone_faces = np.asarray(cone.faces)[:, ::-1]  # the mirror turned them inward
    tip = np.argmin(tip_down[:, 2])
    cone_vertices = tip_down - tip_down[tip] + 1.0 + lift
    vertices = np.concatenate([cube.vertices, cone_vertices])
    return vertices, np.concatenate([cube.faces, cone_faces + len(cube.vertices)]).astype(np.int32)


CLOSED = {"sphere", "box", "torus", "spot", "fandisk", "homer", "rocker-arm", "armadillo-86k"}


def surface_samples(vertices: np.ndarray, faces: np.ndarray, per_face: int, rng: np.random.Generator) -> np.ndarray:
    """Random points on every face (uniform barycentric), plus the vertices."""
    tri = vertices[faces].astype(np.float64)
    r1, r2 = rng.random((2, len(faces), per_face))
    flip = r1 + r2 > 1.0
    r1, r2 = np.where(flip, 1.0 - r1, r1), np.where(flip, 1.0 - r2, r2)
    samples = tri[:, None, 0] + r1[..., None] * (tri[:, None, 1] - tri[:, None, 0]) + r2[..., None] * (
        tri[:, None, 2] - tri[:, None, 0]
    )
    return np.concatenate([samples.reshape(-1, 3), vertices.astype(np.float64)])
