"""The winding walks' budget (WINDING_BUDGET): a sound surface never meets it, and a soup of large triangles, whose
walks would otherwise open nearly every node at every corner, is cut short there with its distances still exact."""

from __future__ import annotations

import numpy as np
import pytest

import meshes
import oracle
import tolerances as tol
from badf.server.adf import DistanceField
from badf.server.adf import _bvh


def soup(count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` random triangles across the unit cube, none sharing a vertex: every node of a tree over them is near
    every point."""
    vertices = np.random.default_rng(seed).random((3 * count, 3)).astype(np.float32)
    return vertices, np.arange(3 * count, dtype=np.int32).reshape(-1, 3)


@pytest.mark.parametrize("name", ["spot", "homer", "torus", "sheet"])
def test_no_walk_of_a_sound_surface_is_cut(device, name):
    """At the default budget (2048 nodes opened; the shared meshes' corner walks opened fewer than 512 at depths 5,
    7 and 9), no walk of a sound surface's frame is cut, and its corners' signs are the oracle's."""
    vertices, faces = meshes.load(name) if name in ("spot", "homer") else meshes.GENERATED[name]()
    field = DistanceField(vertices, faces, depth=6, sign="winding", device=device)
    assert field.stats()["winding_walks_cut"] == 0
    positions, values, _ = field.corner_samples()
    pick = np.random.default_rng(0).choice(len(positions), min(len(positions), 3000), replace=False)
    w = oracle.winding_number(positions[pick], vertices.astype(np.float64), faces)
    off_surface = np.abs(values[pick]) > tol.SIGN_MARGIN * oracle.bbox_diagonal(vertices)
    clear = off_surface & (np.abs(np.abs(w) - 0.5) > tol.WINDING_CONFIDENCE)
    np.testing.assert_array_equal(values[pick][clear] < 0, np.abs(w[clear]) > 0.5)


def test_a_soup_frame_is_cut_short_with_its_distances_exact(device, monkeypatch):
    """A budget below what a soup's walks need cuts them (counted per frame); the distances' magnitudes, which the
    searches give, are those of an uncut twin bit for bit and the oracle's, and every value is finite."""
    vertices, faces = soup(400, seed=3)
    budgets = {"cut": 8, "uncut": 2**30}
    fields = {}
    for label, budget in budgets.items():
        monkeypatch.setattr(_bvh, "WINDING_BUDGET", budget)
        fields[label] = DistanceField(vertices, faces, depth=4, sign="winding", device=device)
    cut, uncut = fields["cut"], fields["uncut"]
    assert cut.stats()["winding_walks_cut"] > 0
    assert uncut.stats()["winding_walks_cut"] == 0

    positions, values, _ = cut.corner_samples()
    _, uncut_values, _ = uncut.corner_samples()
    assert np.isfinite(values).all()
    np.testing.assert_array_equal(np.abs(values), np.abs(uncut_values))
    diagonal = oracle.bbox_diagonal(vertices)
    truth = oracle.signed_distance(positions, vertices.astype(np.float64), faces, signed=False)
    assert np.max(np.abs(np.abs(values) - truth)) <= tol.EXACT_DISTANCE * diagonal

    points = np.random.default_rng(4).random((500, 3)) * 1.2 - 0.1
    truth = oracle.signed_distance(points, vertices.astype(np.float64), faces, signed=False)
    for mode in ("exact", "adf"):
        got = cut.query(points, mode=mode, outputs=("distance", "normal", "closest_point")).distance
        assert np.isfinite(got).all()
        if mode == "exact":
            assert np.max(np.abs(np.abs(got) - truth)) <= tol.EXACT_DISTANCE * diagonal



def test_a_closed_mesh_thrown_into_a_soup_counts_its_cut_walks(device, monkeypatch):
    """A closed mesh is signed by pseudonormals until a frame runs parts into each other; that frame is signed by
    winding numbers, which the budget cuts short when the frame is a soup. The next sound frame cuts none."""
    monkeypatch.setattr(_bvh, "WINDING_BUDGET", 128)  # the sphere's walks (its frames' overlap watch) need fewer
    vertices, faces = meshes.sphere()
    field = DistanceField(vertices, faces, depth=4, device=device)
    assert field.stats()["winding_walks_cut"] == 0
    thrown = vertices + np.random.default_rng(5).uniform(-0.6, 0.6, vertices.shape).astype(np.float32)
    field.update(thrown)
    assert field.stats()["winding_walks_cut"] > 0
    _, values, _ = field.corner_samples()
    assert np.isfinite(values).all()
    field.update(vertices)
    assert field.stats()["winding_walks_cut"] == 0
