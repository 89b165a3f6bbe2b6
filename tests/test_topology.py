"""The engine's topology analysis against a plain reference: the same welding, edges, orientation checks
and adjacency lists, field for field, on meshes with seams, holes, repeated vertices, non-manifold and
inconsistently oriented edges, and -0.0 beside 0.0."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import meshes
import oracle
from badf.server.adf._sign import (RIM_LIMIT, _stable_order, analyse_topology, face_components, face_volumes,
                                 ids_by_weld, rim_fans, with_fans)


def reference_topology(faces: np.ndarray, vertices: np.ndarray) -> dict:
    """The same analysis written the obvious way (np.unique by rows and by keys, numpy's stable sorts)."""
    m = len(faces)
    _, welded_id, welded_count = np.unique(vertices + 0.0, axis=0, return_inverse=True, return_counts=True)
    vertex_count = len(welded_count)
    f = welded_id.reshape(-1)[faces].astype(np.int64)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    end = np.roll(f, -1, axis=1)
    keys = np.minimum(f, end) * vertex_count + np.maximum(f, end)
    usable = np.repeat(~repeated[:, None], 3, axis=1)
    edge_keys, inverse, counts = np.unique(keys[usable], return_inverse=True, return_counts=True)
    edge_count = len(edge_keys)
    face_edge = np.full((m, 3), edge_count, dtype=np.int32)
    face_edge[usable] = inverse
    orientation_sum = np.bincount(inverse, weights=np.where(f < end, 1, -1)[usable], minlength=edge_count)
    face_of_slot = np.repeat(np.arange(m), 3).reshape(m, 3)[usable]
    edge_face_start = np.zeros(edge_count + 2, dtype=np.int32)
    edge_face_start[1 : edge_count + 1] = np.cumsum(counts)
    edge_face_start[edge_count + 1] = edge_face_start[edge_count]
    corner_fan = reference_fans(f, ~repeated)
    fan_count = int(corner_fan.max()) + 1
    fan_corner_start = np.zeros(fan_count + 1, dtype=np.int32)
    fan_corner_start[1:] = np.cumsum(np.bincount(corner_fan.reshape(-1), minlength=fan_count))
    return {
        "welded_faces": f.astype(np.int32),
        "welded_count": vertex_count,
        "face_edge": face_edge,
        "edge_count": edge_count,
        "edge_face_start": edge_face_start,
        "edge_face": face_of_slot[np.argsort(inverse, kind="stable")].astype(np.int32),
        "corner_fan": corner_fan,
        "fan_count": fan_count,
        "fan_corner_start": fan_corner_start,
        "fan_corner": np.argsort(corner_fan.reshape(-1), kind="stable").astype(np.int32),
        "boundary_edges": int(np.sum(counts == 1)),
        "nonmanifold_edges": int(np.sum(counts > 2)),
        "inconsistent_edges": int(np.sum((counts == 2) & (orientation_sum != 0))),
        "repeated_vertex_faces": int(np.sum(repeated)),
        "seam_pairs": reference_seam_pairs(np.asarray(faces), corner_fan),
        "rim_edges": np.stack([edge_keys // vertex_count, edge_keys % vertex_count, orientation_sum.astype(np.int64)],
                              axis=1)[orientation_sum != 0],
    }


def reference_seam_pairs(faces: np.ndarray, corner_fan: np.ndarray) -> np.ndarray:
    """(K, 2): each vertex id at a corner whose fan's smallest corner names another id, with that id, sorted."""
    raw, fan = faces.reshape(-1).tolist(), corner_fan.reshape(-1).tolist()
    first: dict[int, int] = {}
    for corner, k in enumerate(fan):
        first.setdefault(k, raw[corner])
    pairs = sorted({(v, first[k]) for v, k in zip(raw, fan) if v != first[k]})
    return np.array(pairs, dtype=np.int32).reshape(-1, 2)


def reference_fans(welded_faces: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(M, 3) fan of each corner: a Python union-find joining the corners at the same welded vertex of faces
    that share an edge; fans numbered by (welded vertex, smallest corner)."""
    m = len(welded_faces)
    parent = list(range(3 * m))

    def find(x: int) -> int:
        while parent[x] != x:
            x = parent[x]
        return x

    faces_of_edge: dict[tuple[int, int], list[int]] = {}
    for face in np.flatnonzero(usable):
        for k in range(3):
            a, b = int(welded_faces[face, k]), int(welded_faces[face, (k + 1) % 3])
            faces_of_edge.setdefault((min(a, b), max(a, b)), []).append(int(face))
    for (a, b), faces in faces_of_edge.items():
        for vertex in (a, b):
            corners = [3 * face + int(np.flatnonzero(welded_faces[face] == vertex)[0]) for face in faces]
            for corner in corners[1:]:
                low, high = sorted((find(corners[0]), find(corner)))
                parent[high] = low
    root = np.array([find(c) for c in range(3 * m)])
    key = welded_faces.reshape(-1).astype(np.int64)[root] * (3 * m) + root
    return np.unique(key, return_inverse=True)[1].reshape(m, 3).astype(np.int32)


def _awkward() -> tuple[np.ndarray, np.ndarray]:
    """A sphere with a seam of duplicated vertices (one at -0.0), a flipped face, a fin on one edge (three
    faces there), a face naming a vertex twice, and a hole."""
    vertices, faces = meshes.sphere()
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64).copy()
    zero = np.flatnonzero(vertices[:, 0] == 0.0)[:1]
    copies = np.concatenate([vertices[:40], vertices[zero] * np.array([-1.0, 1.0, 1.0])])  # -0.0 in x
    seam = np.arange(len(vertices), len(vertices) + 40)
    vertices = np.concatenate([vertices, copies])
    faces[:20] = np.where(faces[:20] < 40, seam[np.minimum(faces[:20], 39)], faces[:20])  # seam: same positions
    faces[30] = faces[30, ::-1]  # flipped
    a, b = faces[50, 0], faces[50, 1]
    extra = np.array([[a, b, len(vertices) - 1], [a, a, b]])  # fin, repeated vertex
    faces = np.concatenate([np.delete(faces, [60, 61], axis=0), extra])  # and a hole
    return vertices, faces


CASES = {
    "bunny": lambda: meshes.load("stanford-bunny"),
    "spot (UV seams)": lambda: meshes.load("spot"),
    "sheet": meshes.sheet,
    "single triangle": meshes.single_triangle,
    "awkward sphere": _awkward,
    "parts touching at a point": meshes.cone_on_cube,
    "parts apart": lambda: _apart(),
}


def _apart() -> tuple[np.ndarray, np.ndarray]:
    """A torus, a box beside it and a cone on a cube lifted off it: four parts, the faces of each interleaved."""
    parts = [meshes.torus(), meshes.box(), meshes.cone_on_cube(lift=0.5)]
    vertices, faces, offset = [], [], 0
    for k, (v, f) in enumerate(parts):
        vertices.append(np.asarray(v, np.float64) + [3.0 * k, 0.0, 0.0])
        faces.append(np.asarray(f, np.int64) + offset)
        offset += len(v)
    faces = np.concatenate(faces)
    return np.concatenate(vertices), faces[np.random.default_rng(0).permutation(len(faces))]


@pytest.mark.parametrize("name", list(CASES))
def test_topology_matches_the_reference(name):
    vertices, faces = CASES[name]()
    got = dataclasses.asdict(analyse_topology(np.asarray(faces), np.asarray(vertices)))
    expected = reference_topology(np.asarray(faces), np.asarray(vertices))
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        np.testing.assert_array_equal(got[key], value, err_msg=key)


@pytest.mark.parametrize("name", list(CASES))
def test_fans_added_later_are_the_fans_analysed_at_once(name):
    """A field that pseudonormals will not sign leaves the fans out (half of the analysis); `with_fans` adds them
    to such a topology, field for field as one analysis with them gives, and the rest is the same either way."""
    vertices, faces = (np.asarray(a) for a in CASES[name]())
    whole = dataclasses.asdict(analyse_topology(faces, vertices))
    edges_only = analyse_topology(faces, vertices, fans=False)
    assert not edges_only.has_fans and len(faces) > 0
    later = dataclasses.asdict(with_fans(edges_only, faces))
    for key, value in whole.items():
        np.testing.assert_array_equal(later[key], value, err_msg=key)
    for key in ("welded_faces", "face_edge", "edge_face_start", "edge_face", "boundary_edges", "inconsistent_edges"):
        np.testing.assert_array_equal(dataclasses.asdict(edges_only)[key], whole[key], err_msg=key)


def test_the_awkward_sphere_has_every_defect():
    """So that the comparison above covers each branch of the analysis."""
    vertices, faces = _awkward()
    topology = analyse_topology(faces, vertices)
    assert topology.boundary_edges > 0 and topology.nonmanifold_edges > 0
    assert topology.inconsistent_edges > 0 and topology.repeated_vertex_faces > 0
    assert topology.welded_count < len(vertices)  # the seam and the -0.0 copy were welded
    assert len(topology.seam_pairs) > 0  # which a frame must keep together for the pseudonormals to hold


def test_parts_touching_at_a_point_get_a_fan_each():
    """The cone's tip and the cube's corner weld into one vertex, whose corners make two fans."""
    vertices, faces = meshes.cone_on_cube()
    topology = analyse_topology(faces, vertices)
    assert topology.closed
    assert topology.fan_count == topology.welded_count + 1
    assert len(topology.seam_pairs) == 0  # the parts may move apart


@pytest.mark.parametrize("top", [0, 1, 2**16 - 1, 2**16, 2**31 - 1, 2**40, 2**62])
def test_the_radix_order_is_numpys_stable_sort(top):
    """The analysis sorts its keys by 16-bit digits (`_stable_order`): the order numpy's stable sort gives, ties kept
    in index order, for keys of one to four digits; shuffled, nearly sorted and with many repeats."""
    rng = np.random.default_rng(top % 1000)
    shuffled = rng.integers(0, top + 1, 5000, dtype=np.int64)
    repeats = rng.choice(shuffled[:7], 5000)
    nearly = np.sort(shuffled) + rng.integers(0, 2, 5000) * (top > 0)
    for keys in (shuffled, repeats, np.minimum(nearly, top), shuffled.astype(np.int32) if top < 2**31 else shuffled):
        np.testing.assert_array_equal(_stable_order(keys), np.argsort(keys, kind="stable"))
    assert len(_stable_order(np.zeros(0, np.int64))) == 0


@pytest.mark.parametrize("name", list(CASES))
def test_face_volumes_and_parts_match_the_reference(name):
    """Each face's volume with the origin and area (float64, within rounding of np.cross), and the parts that
    shared positions connect (a plain flood fill over the welded faces)."""
    vertices, faces = (np.asarray(a) for a in CASES[name]())
    volume, area = face_volumes(vertices, faces)
    v = vertices.astype(np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    scale = np.max(np.abs(v)) ** 3
    np.testing.assert_allclose(volume, np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0, rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(area, np.linalg.norm(np.cross(b - a, c - a), axis=1) / 2.0, rtol=1e-14)
    topology = analyse_topology(faces, vertices)
    parent = list(range(topology.welded_count))  # a plain union-find over the welded vertices

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b, c in topology.welded_faces.tolist():
        for i, j in ((a, b), (b, c)):
            parent[max(root(i), root(j))] = min(root(i), root(j))
    expected = np.array([root(a) for a in topology.welded_faces[:, 0].tolist()])
    labels = face_components(topology)
    assert labels.min() == 0 and labels.max() == len(np.unique(expected)) - 1  # numbered 0..parts-1

    def by_first_face(x):  # labels renumbered in the order their first face comes, to compare partitions
        _, first, inverse = np.unique(x, return_index=True, return_inverse=True)
        rank = np.empty(len(first), dtype=np.int64)
        rank[np.argsort(first)] = np.arange(len(first))
        return rank[inverse.reshape(-1)]

    np.testing.assert_array_equal(by_first_face(labels), by_first_face(expected))


@pytest.mark.parametrize("name", list(CASES))
def test_the_rim_fans_close_the_boundary_so_winding_numbers_add_up_to_whole_numbers(name):
    """With `rim_fans`' fans, any mesh (holes, a seam left unwelded, a fin, a flipped face, a face naming a vertex
    twice, a sheet, a lone triangle) bounds nothing: the float64 oracle's winding number of faces and fans together
    is a whole number at points off both, which is what lets the engine correct a walk's w near 1/2. Meshes with a
    boundary are the ones whose own winding numbers are not whole, so the check can fail."""
    vertices, faces = (np.asarray(a) for a in CASES[name]())
    fans = rim_fans(faces)
    v = vertices.astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    points = np.random.default_rng(11).uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), (200, 3))
    own = oracle.winding_number(points, v, faces)
    both = own + oracle.winding_number(points, v, fans)
    np.testing.assert_allclose(both, np.round(both), rtol=0, atol=1e-9)
    if analyse_topology(faces, vertices).summary()["boundary_edges"] > 0:
        assert len(fans) > 0 and np.max(np.abs(own - np.round(own))) > 1e-3
        assert rim_fans(faces, limit=0) is None  # past the limit: no fans, and the walk's w stays


@pytest.mark.parametrize("name", [*CASES, "armadillo", "spot welded", "horse", "bunny renamed"])
def test_the_rim_from_the_topology_is_the_rim_the_sort_finds(name):
    """`rim_fans` given the topology takes the edges from it, with no sort of its own, where the weld joined none of
    the faces' vertex ids. Its fans must be the sort's, bit for bit: where a weld joined ids (spot's UV seams, a
    cone's tip welded to a cube's corner, the awkward sphere's seam) it sorts as before."""
    if name == "armadillo":
        vertices, faces = meshes.load("armadillo-86k")
    elif name == "horse":
        vertices, faces = meshes.load("sumner_horse_gallop")
    elif name == "spot welded":  # spot's seams joined in the faces themselves: closed, and nothing left to weld
        vertices, faces = meshes.load("spot")
        welded = analyse_topology(faces, vertices, fans=False)
        joined = np.empty((welded.welded_count, 3), dtype=vertices.dtype)
        joined[welded.welded_faces] = vertices[faces]
        vertices, faces = joined, welded.welded_faces
    elif name == "bunny renamed":  # ids shuffled against the positions' order, so the renaming turns edges round
        vertices, faces = meshes.load("stanford-bunny")
        shuffle = np.random.default_rng(5).permutation(len(vertices))
        vertices, faces = vertices[np.argsort(shuffle)], shuffle[faces]
    else:
        vertices, faces = (np.asarray(a) for a in CASES[name]())
    topology = analyse_topology(faces, vertices, fans=False)
    renamed = ids_by_weld(topology, faces) is not None
    assert renamed == (name not in ("spot (UV seams)", "parts touching at a point", "awkward sphere"))
    for limit in (0, 10, RIM_LIMIT):
        by_topology, by_sort = rim_fans(faces, limit, topology=topology), rim_fans(faces, limit)
        assert (by_topology is None) == (by_sort is None)
        if by_sort is not None:
            np.testing.assert_array_equal(by_topology, by_sort)
