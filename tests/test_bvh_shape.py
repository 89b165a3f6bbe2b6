"""The BVH shaped by the surface area heuristic (bvh="sah"): a tree over every triangle within the searches' depth,
and fields whose distances are the Morton tree's, exact against the float64 oracle, with and without coherence."""

from __future__ import annotations

import numpy as np
import pytest

import meshes
import oracle
import tolerances as tol
from badf.server.adf import DistanceField, InvalidInputError
from badf.server.adf import _bvh_shape
from badf.server.adf._bvh_shape import MAX_DEPTH, sah_shape


def _soup(centres: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """A small triangle at each centre."""
    corners = np.array([[0.0, 0.0, 0.0], [size, 0.0, 0.0], [0.0, size, 0.0]])
    vertices = (centres[:, None, :] + corners[None]).reshape(-1, 3)
    return vertices, np.arange(len(vertices)).reshape(-1, 3)


def _doubling(count: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Triangle k at 2^k along x, 2^k across."""
    scale = 2.0 ** np.arange(count)
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    vertices = ((corners[None] + np.array([1.0, 0.0, 0.0])) * scale[:, None, None]).reshape(-1, 3)
    return vertices, np.arange(len(vertices)).reshape(-1, 3)


def _cases() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(5)
    return {
        "spot": meshes.load("spot"),
        "stanford-bunny": meshes.load("stanford-bunny"),
        "two triangles": _soup(np.array([[0.0, 0, 0], [1, 0, 0]]), 0.1),
        "three triangles": _soup(np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0]]), 0.1),
        "one triangle 200 times": _soup(np.zeros((200, 3)), 1.0),
        "a line of needles": _soup(np.column_stack([np.arange(300.0), np.zeros(300), np.zeros(300)]), 1e-6),
        # each split by area takes off the largest and farthest: the depth cap makes it split evenly in time
        "doubling": _doubling(),
        "random soup": _soup(rng.normal(size=(1000, 3)) * rng.uniform(1e-3, 10, size=(1000, 1)), 1e-2),
    }


CASES = _cases()


@pytest.mark.parametrize("name", list(CASES))
def test_sah_shape_is_a_tree_over_every_triangle_within_the_searches_depth(name):
    vertices, faces = CASES[name]
    n = len(faces)
    shape = sah_shape(vertices, faces)
    assert np.array_equal(np.sort(shape.order), np.arange(n))
    # every node but the root is the child of exactly one internal node
    children = np.concatenate([shape.left, shape.right])
    assert np.array_equal(np.sort(children), np.arange(1, 2 * n - 1))

    def leaf_range(child):
        return (child - (n - 1), child - (n - 1)) if child >= n - 1 else (shape.first[child], shape.last[child])

    left = np.array([leaf_range(c) for c in shape.left])
    right = np.array([leaf_range(c) for c in shape.right])
    # a node's leaves are its left child's, then its right child's
    assert np.array_equal(left[:, 0], shape.first) and np.array_equal(right[:, 1], shape.last)
    assert np.array_equal(left[:, 1] + 1, right[:, 0])
    assert shape.first[0] == 0 and shape.last[0] == n - 1
    # the deepest leaf, counted from the root
    depth = np.zeros(2 * n - 1, np.int64)
    for node in range(n - 1):  # ids grow with depth: a parent's id is below its children's
        depth[shape.left[node]] = depth[shape.right[node]] = depth[node] + 1
    assert int(depth.max()) == shape.depth <= MAX_DEPTH


def _root_split_by_area(vertices: np.ndarray, faces: np.ndarray) -> int:
    """The root's left count by the heuristic, worked out in numpy: the triangles binned along the longest axis of
    their centroids' bounds (32 even bins, or a bin each by rank along it for at most 32), and the first cut
    between bins with the least sum of box area times count on each side."""
    corners = vertices[faces].astype(np.float64)
    lower, upper, centre = corners.min(axis=1), corners.max(axis=1), corners.mean(axis=1)
    axis = int(np.argmax(centre.max(axis=0) - centre.min(axis=0)))
    along = centre[:, axis] - centre[:, axis].min()
    n = len(faces)
    if n <= _bvh_shape.BINS:
        bins = np.empty(n, np.int64)
        bins[np.argsort(along, kind="stable")] = np.arange(n)
    else:
        bins = np.minimum((along / along.max() * _bvh_shape.BINS).astype(np.int64), _bvh_shape.BINS - 1)

    def half_area(members):
        d = upper[members].max(axis=0) - lower[members].min(axis=0)
        return d[0] * d[1] + d[1] * d[2] + d[2] * d[0]

    costs = []
    for cut in range(int(bins.max())):
        on_left = bins <= cut
        if 0 < on_left.sum() < n:
            costs.append((half_area(on_left) * on_left.sum() + half_area(~on_left) * (~on_left).sum(), on_left.sum()))
    return int(min(costs, key=lambda c: c[0])[1])


@pytest.mark.parametrize("count", [7, 32, 33, 1000])
def test_the_root_is_split_where_the_heuristic_costs_least(count):
    rng = np.random.default_rng(count)
    # denser towards 0, so that the least cost falls between even fractions of the axis, where the bins differ
    centres = rng.uniform(size=(count, 3)) ** 2 * np.array([3.0, 1.0, 0.5])
    sizes = rng.uniform(0.01, 1.0, size=count)
    vertices = (centres[:, None, :] + rng.normal(size=(count, 3, 3)) * sizes[:, None, None]).reshape(-1, 3)
    faces = np.arange(3 * count).reshape(-1, 3)
    shape = sah_shape(vertices, faces)
    left_count = 1 if shape.left[0] >= count - 1 else shape.last[shape.left[0]] - shape.first[shape.left[0]] + 1
    assert left_count == _root_split_by_area(vertices, faces)
    # the left side holds the triangles of the bins before the cut: the leaves' order puts them first
    along = vertices[faces].mean(axis=1)[:, np.argmax(np.ptp(vertices[faces].mean(axis=1), axis=0))]
    assert along[shape.order[:left_count]].max() <= along[shape.order[left_count:]].min()


@pytest.mark.parametrize("name", ["stanford-bunny", "doubling", "random soup", "one triangle 200 times"])
def test_the_subtrees_built_side_by_side_make_the_same_tree(name, monkeypatch):
    """Below the top of the tree, subtrees are shared out over threads: the tree is the one thread's, whatever the
    count (a small grain here, so that the soups are shared out too)."""
    monkeypatch.setattr(_bvh_shape, "_SHARED_GRAIN", 16)
    vertices, faces = CASES[name]
    alone = sah_shape(vertices, faces, threads=1)
    for threads in (2, 5):
        shared = sah_shape(vertices, faces, threads=threads)
        for a, b in zip(alone, shared):
            assert np.array_equal(a, b)


def test_the_depth_cap_splits_evenly_where_area_would_go_deeper(monkeypatch):
    vertices, faces = CASES["doubling"]
    assert sah_shape(vertices, faces).depth <= MAX_DEPTH
    monkeypatch.setattr(_bvh_shape, "MAX_DEPTH", 10_000)
    assert sah_shape(vertices, faces).depth > MAX_DEPTH  # what area alone makes of it


@pytest.mark.parametrize(("name", "depth"), [("spot", 5), ("stanford-bunny", 5), ("sheet", 5), ("torus", 4)])
def test_sah_fields_have_the_morton_fields_distances_and_are_exact(device, name, depth):
    """Over frames, one of them moving the domain (the SAH tree is kept, its keys sorted again): every corner's and
    exact query's distance is the Morton tree's (the searches find the least over every triangle whatever the
    tree), exact against the oracle, and the same without coherence (whose searches start from the keys)."""
    vertices, faces = meshes.load(name)
    morton = DistanceField(vertices, faces, depth=depth, bvh="morton", device=device)
    sah = DistanceField(vertices, faces, depth=depth, bvh="sah", device=device)
    sah_alone = DistanceField(vertices, faces, depth=depth, bvh="sah", coherence=False, device=device)
    assert sah.info()["bvh"] == "sah" and morton.info()["bvh"] == "morton"
    assert sah.stats()["bvh_shape_ms"] > 0 and morton.stats()["bvh_shape_ms"] is None
    rng = np.random.default_rng(17)
    frames = [vertices * np.float32(1.02), vertices + np.float32(0.01), vertices * np.float32(2.5) + np.float32(3.0)]
    for frame in frames:
        for field in (morton, sah, sah_alone):
            field.update(frame)
        diag = oracle.bbox_diagonal(frame)
        positions, values, nearest = sah.corner_samples()
        _, morton_values, _ = morton.corner_samples()
        _, alone_values, _ = sah_alone.corner_samples()
        if device == "cpu":
            np.testing.assert_array_equal(np.abs(values), np.abs(morton_values))
            np.testing.assert_array_equal(values, alone_values)
        else:  # CUDA rounds a seed's distance and a walk's apart by an ulp (see test_engine's coherence test)
            assert np.all(np.abs(np.abs(values) - np.abs(morton_values)) <= tol.EXACT_DISTANCE * diag)
            assert np.all(np.abs(values - alone_values) <= tol.EXACT_DISTANCE * diag)
        pick = rng.choice(len(positions), min(400, len(positions)), replace=False)
        truth = oracle.nearest(positions[pick], frame, faces)
        assert np.all(np.abs(np.abs(values[pick]) - truth.distance) <= tol.EXACT_DISTANCE * diag)
        # the face a corner keeps realises its distance (of faces that tie, each tree names its own first leaf)
        own = distance_to_own_face(positions[pick], frame, faces, nearest[pick])
        assert np.all(np.abs(own - truth.distance) <= tol.EXACT_DISTANCE * diag)
        points = frame[rng.choice(len(frame), 300)] + rng.normal(scale=0.05 * diag, size=(300, 3))
        got = sah.query(points, mode="exact", outputs=("distance", "face"))
        expected = morton.query(points, mode="exact").distance
        np.testing.assert_allclose(np.abs(got.distance), np.abs(expected), rtol=0, atol=tol.EXACT_DISTANCE * diag)
        truth = oracle.nearest(points, frame, faces)
        assert np.all(np.abs(np.abs(got.distance) - truth.distance) <= tol.EXACT_DISTANCE * diag)
        w = oracle.winding_number(points, frame, faces)
        clear = (truth.distance > tol.SIGN_MARGIN * diag) & (np.abs(np.abs(w) - 0.5) > 0.1)
        assert np.array_equal((got.distance < 0)[clear], (np.abs(w) > 0.5)[clear])
    assert sah.stats()["domain_moves"] == morton.stats()["domain_moves"] >= 1  # the third frame moved it


def distance_to_own_face(points, vertices, faces, face) -> np.ndarray:
    tri = vertices[faces[face]].astype(np.float64)
    return np.linalg.norm(points - oracle.closest_points_on_triangles(points, tri[:, 0], tri[:, 1], tri[:, 2]), axis=1)


def test_auto_takes_the_sah_tree_on_the_cpu_and_mortons_on_cuda(device):
    vertices, faces = meshes.load("spot")
    field = DistanceField(vertices, faces, depth=3, device=device)
    expected = "sah" if device == "cpu" else "morton"
    assert field.info()["bvh"] == expected and field.info()["bvh_requested"] == "auto"
    assert (field.stats()["bvh_shape_ms"] is not None) == (expected == "sah")
    asked = DistanceField(vertices, faces, depth=3, bvh=expected, device=device)
    points = vertices[::50] + np.float32(0.05)
    np.testing.assert_array_equal(field.query(points, mode="exact", outputs=("distance", "face")).face,
                                  asked.query(points, mode="exact", outputs=("distance", "face")).face)


def test_sah_is_refused_clearly_where_warp_cannot_run_its_cpu_builder(device, monkeypatch):
    """The SAH tree is made on Warp's CPU back-end whatever the device: a Warp without its CPU compiler (as a GPU
    machine's may be installed) gets a clear refusal naming the way out, not an error from inside Warp."""
    vertices, faces = meshes.load("box")
    monkeypatch.setattr(_bvh_shape.wp, "is_cpu_available", lambda: False)
    with pytest.raises(InvalidInputError, match="bvh='sah' makes its tree on Warp's CPU back-end.*use bvh='morton'"):
        DistanceField(vertices, faces, depth=3, bvh="sah", device=device)
    if device != "cpu":  # the radix tree needs no CPU back-end
        DistanceField(vertices, faces, depth=3, bvh="auto", device=device)


def test_the_bvh_shape_is_checked_and_a_single_triangle_needs_none(device):
    vertices, faces = meshes.load("single-triangle")
    with pytest.raises(InvalidInputError, match="bvh must be one of auto, morton, sah; got 'kd'"):
        DistanceField(vertices, faces, depth=3, bvh="kd", device=device)
    field = DistanceField(vertices, faces, depth=3, bvh="sah", device=device)
    points = np.array([[0.2, 0.2, 0.5], [3.0, -1.0, 0.0]])
    truth = oracle.nearest(points, vertices, faces).distance
    assert np.allclose(np.abs(field.query(points, mode="exact").distance), truth,
                       atol=tol.EXACT_DISTANCE * oracle.bbox_diagonal(vertices))
