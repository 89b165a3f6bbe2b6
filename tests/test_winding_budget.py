"""The winding walks' budget (WINDING_BUDGET): it binds only a soup (SOUP_AREA) or a tree that misfits its frame, so
a sound surface's walks run whole, also where they open more nodes than the budget (long thin triangles), and a soup of
large triangles, whose walks would otherwise open nearly every node at every corner, is cut short there with its
distances still exact. A Morton tree linked on such a soup, which misfits the calm frames after it, is linked again
(`bvh_relinks`)."""

from __future__ import annotations

import numpy as np
import pytest

import meshes
import oracle
import tolerances as tol
from badf.bench._cases import folded_sheet
from badf.server.adf import DistanceField
from badf.server.adf import _bvh


def soup(count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` random triangles across the unit cube, none sharing a vertex: every node of a tree over them is near
    every point."""
    vertices = np.random.default_rng(seed).random((3 * count, 3)).astype(np.float32)
    return vertices, np.arange(3 * count, dtype=np.int32).reshape(-1, 3)


def slivers():
    """A closed cylinder of 2,000 sections: 8,000 triangles as long as the cylinder (or its radius) and 1/600 as wide.
    Every node of a tree over them is near every point beside the cylinder, so its walks open nearly all 7,999."""
    return meshes.wire(radius=0.5, height=2.0, sections=2000)


@pytest.mark.parametrize("name", ["spot", "homer", "torus", "sheet", "slivers", "folded"])
def test_no_walk_of_a_sound_surface_is_cut(device, name):
    """No walk of a sound surface's frame is cut, and its corners' signs are the oracle's: the shared meshes' corner
    walks open fewer than 512 nodes (at depths 5, 7 and 9), the slivers' more than the budget (2,048), and run whole.
    The folded sheet counts as a soup by its area, but its nodes of long strips are thin (FAT_AREA): none counts."""
    generated = {"slivers": slivers, "folded": folded_sheet}
    vertices, faces = generated[name]() if name in generated else meshes.load(name)
    field = DistanceField(vertices, faces, depth=5 if name in generated else 6, sign="winding", device=device)
    assert field.stats()["winding_walks_cut"] == 0
    positions, values, _ = field.corner_samples()
    pick = np.random.default_rng(0).choice(len(positions), min(len(positions), 3000), replace=False)
    w = oracle.winding_number(positions[pick], vertices.astype(np.float64), faces)
    off_surface = np.abs(values[pick]) > tol.SIGN_MARGIN * oracle.bbox_diagonal(vertices)
    clear = off_surface & (np.abs(np.abs(w) - 0.5) > tol.WINDING_CONFIDENCE)
    np.testing.assert_array_equal(values[pick][clear] < 0, np.abs(w[clear]) > 0.5)
    field.query(positions[pick[:200]], mode="exact")
    assert field.stats()["last_query_walks_cut"] == 0


@pytest.mark.parametrize("name", ["slivers", "folded"])
def test_thin_walks_would_meet_the_budget_if_every_node_counted(device, monkeypatch, name):
    """The slivers' and the folded sheet's walks do open more than the budget: counted as a soup (SOUP_AREA 0, which
    every surface passes) with every node counting (FAT_AREA 0), their frames cut them. The slivers' surface is 0.42
    of its root's sphere's area, the folded sheet's 11.8."""
    monkeypatch.setattr(_bvh, "SOUP_AREA", 0.0)
    monkeypatch.setattr(_bvh, "FAT_AREA", 0.0)
    vertices, faces = slivers() if name == "slivers" else folded_sheet()
    field = DistanceField(vertices, faces, depth=4, sign="winding", device=device)
    assert field.stats()["winding_walks_cut"] > 0


def test_a_soup_frame_is_cut_short_with_its_distances_exact(device, monkeypatch):
    """A budget below what a soup's walks need cuts them (counted per frame); the distances' magnitudes, which the
    searches give, are those of an uncut twin bit for bit and the oracle's, and every value is finite. (2,000 random
    triangles in the unit cube: 32 times their root's sphere's area, a soup; 400 of them are 6.4 times, which is not.)"""
    vertices, faces = soup(2000, seed=3)
    budgets = {"cut": 8, "uncut": 2**30}
    fields = {}
    for label, budget in budgets.items():
        monkeypatch.setattr(_bvh, "WINDING_BUDGET", budget)
        fields[label] = DistanceField(vertices, faces, depth=4, sign="winding", device=device)
    cut, uncut = fields["cut"], fields["uncut"]
    frame_cuts = cut.stats()["winding_walks_cut"]
    assert frame_cuts > 0
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
            # an exact query signs each point by a walk of its own, cut as the frame's are, and counted apart
            assert cut.stats()["last_query_walks_cut"] > 0
            assert cut.stats()["winding_walks_cut"] == frame_cuts
            assert uncut.query(points, mode=mode).distance.shape == (500,)
            assert uncut.stats()["last_query_walks_cut"] == 0



def test_a_closed_mesh_thrown_into_a_soup_counts_its_cut_walks(device, monkeypatch):
    """A closed mesh is signed by pseudonormals until a frame runs parts into each other; that frame is signed by
    winding numbers, which the budget cuts short when the frame is a soup. The throw moves the domain, so the tree is
    linked on the soup: the first calm frame after it runs on that tree and the next links it again (on CUDA, 4,096
    walks of the first calm frame's overlap watch met a budget of 128 there). Then no walk is cut."""
    monkeypatch.setattr(_bvh, "WINDING_BUDGET", 128)  # the sphere's walks (its frames' overlap watch) need fewer
    # the sphere's 1,280 triangles thrown pile up 3.2 times the area of the sphere that bounds them: a soup at this bar
    monkeypatch.setattr(_bvh, "SOUP_AREA", 1.0)
    vertices, faces = meshes.sphere()
    field = DistanceField(vertices, faces, depth=4, bvh="morton", device=device)
    assert field.stats()["winding_walks_cut"] == 0
    thrown = vertices + np.random.default_rng(5).uniform(-0.6, 0.6, vertices.shape).astype(np.float32)
    field.update(thrown)
    assert field.stats()["winding_walks_cut"] > 0 and field.stats()["domain_moves"] == 1
    _, values, _ = field.corner_samples()
    assert np.isfinite(values).all()
    field.update(vertices)
    field.update(vertices)
    assert field.stats()["bvh_relinks"] == 1
    assert field.stats()["winding_walks_cut"] == 0


def thrown_out_of_its_box(vertices: np.ndarray, seed: int) -> np.ndarray:
    """Every vertex thrown up to a fifth of the box's extent: a soup, whose box (and domain) is larger."""
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    rng = np.random.default_rng(seed)
    return (vertices + rng.uniform(-0.2, 0.2, vertices.shape) * extent).astype(np.float32)


@pytest.mark.parametrize("name", ["spot", "stanford-bunny"])
def test_a_tree_linked_on_a_soup_is_linked_again_once_the_mesh_is_calm(device, name):
    """A frame that moves the domain links the Morton tree on its own triangles. Linked on a soup and refitted to the
    calm mesh again, its leaves lie far apart, and every walk runs long. A calm frame whose winding walks met their
    budget there is run again at once on a tree linked on itself (the bunny's: 5,701 walks on the CPU); one whose
    walks did not (spot's) links it in the next frame. Then the spread, the walks and the answers are a fresh
    object's."""
    vertices, faces = meshes.load(name)
    field = DistanceField(vertices, faces, depth=5, sign="winding", bvh="morton", device=device)
    calm_spread = field.stats()["bvh_leaf_spread"]
    field.update(thrown_out_of_its_box(vertices, seed=1))
    assert field.stats()["domain_moves"] == 1
    field.update(vertices)
    first = field.stats()
    if first["bvh_relinks"] == 1:  # run again: nothing of the misfit tree is left
        assert first["winding_walks_cut"] == 0 and first["bvh_leaf_spread"] <= 1.1 * calm_spread
    else:  # refitted to the soup's tree, which misfits it, but no walk was cut
        assert first["winding_walks_cut"] == 0 and first["bvh_leaf_spread"] > 2.0 * calm_spread
    if name == "stanford-bunny":
        assert first["bvh_relinks"] == 1
    field.update(vertices)  # the same vertices: a rigid frame, unless the tree is due to be linked again
    relinked = field.stats()
    assert relinked["bvh_relinks"] == 1 and relinked["domain_moves"] == 1
    assert relinked["bvh_leaf_spread"] <= 1.1 * calm_spread and relinked["winding_walks_cut"] == 0
    field.update(vertices)
    assert field.stats()["bvh_relinks"] == 1  # and it stays

    points = np.random.default_rng(2).uniform(vertices.min(axis=0), vertices.max(axis=0), (400, 3))
    truth = oracle.signed_distance(points, vertices.astype(np.float64), faces)
    got = field.query(points, mode="exact").distance
    diagonal = oracle.bbox_diagonal(vertices)
    clear = np.abs(truth) > tol.SIGN_MARGIN * diagonal
    assert np.max(np.abs(np.abs(got) - np.abs(truth))) <= tol.EXACT_DISTANCE * diagonal
    np.testing.assert_array_equal(got[clear] < 0, truth[clear] < 0)


def test_an_animation_refits_its_tree_without_linking_it_again(device):
    """Sixty frames of a dancer refit the tree linked on the first (their spread stays within 8% of it), and the
    SAH tree, whose shape is kept, never measures a spread."""
    frames, faces = meshes.load_sequence("vlasic_samba")
    morton = DistanceField(frames[0], faces, depth=3, bvh="morton", device=device)
    sah = DistanceField(frames[0], faces, depth=3, bvh="sah", device=device)
    for vertices in frames[1:]:
        morton.update(vertices)
        sah.update(vertices)
        assert morton.stats()["bvh_relinks"] == 0
    assert sah.stats()["bvh_relinks"] == 0 and sah.stats()["bvh_leaf_spread"] == 0.0


def test_a_run_of_soups_is_not_run_twice(device):
    """Soups that keep the domain each meet the budget on any tree, and their leaves lie no farther apart than their
    large triangles: a soup on another soup's tree is not run again at once (each would cost twice), and the tree is
    linked every other frame."""
    vertices, faces = meshes.load("spot")
    field = DistanceField(vertices, faces, depth=4, sign="winding", bvh="morton", rigid="off", device=device)
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    lo, hi = vertices.min(axis=0) - 0.1 * extent, vertices.max(axis=0) + 0.1 * extent
    for seed in range(5):
        thrown = vertices + np.random.default_rng(seed).uniform(-0.2, 0.2, vertices.shape) * extent
        field.update(np.clip(thrown, lo, hi).astype(np.float32))
        assert field.stats()["winding_walks_cut"] > 0
    assert field.stats()["domain_moves"] == 1
    assert field.stats()["bvh_relinks"] == 2  # frames 3 and 5; one a frame would be 4
