"""Rigid frames: a frame that only turns and shifts the mesh keeps the field and moves the queries into it.

Every answer is held to the float64 oracle on the moved mesh; a rebuilt twin (rigid="off") given the same frames
says what rebuilding would have answered.
"""

from __future__ import annotations

import numpy as np
import pytest

import meshes
import oracle
import tolerances as tol
from badf.server.adf import DistanceField, InvalidInputError

ALL_OUTPUTS = ("distance", "closest_point", "normal", "face")


def _rotation(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _points(vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator, count: int = 600) -> np.ndarray:
    """Points in and around the box, and points just off the surface."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    pad = 0.2 * (hi - lo)
    spread = rng.uniform(lo - pad, hi + pad, (count, 3))
    surface = meshes.surface_samples(vertices, faces, 1, rng)
    off = 0.01 * np.linalg.norm(hi - lo)
    near = surface[rng.choice(len(surface), count // 2)] + rng.normal(0.0, off, (count // 2, 3))
    return np.concatenate([spread, near])


def _assert_true_to(result, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *, signed: bool) -> None:
    """Exact answers against the float64 oracle on the mesh where this frame puts it."""
    diagonal = oracle.bbox_diagonal(vertices)
    truth = oracle.signed_distance(points, vertices, faces, signed=signed)
    np.testing.assert_allclose(result.distance, truth, rtol=0, atol=tol.EXACT_DISTANCE * diagonal)
    sure = np.abs(truth) > tol.SIGN_MARGIN * diagonal
    if signed:
        assert np.array_equal(np.sign(result.distance[sure]), np.sign(truth[sure]))
    # the closest point realises the distance, and lies on the face named, to float32's rounding where it lies
    # (4e-5 of a unit 1e3 from the origin)
    reach = np.linalg.norm(result.closest_point - points, axis=1)
    rounding = 4 * tol.FLOAT32_INPUT_ROUNDING * float(np.abs(result.closest_point).max())
    np.testing.assert_allclose(reach, np.abs(truth), rtol=0, atol=tol.EXACT_DISTANCE * diagonal + rounding)
    triangles = vertices[faces[result.face]].astype(np.float64)
    on_face = oracle.closest_points_on_triangles(result.closest_point.astype(np.float64), *triangles.transpose(1, 0, 2))
    assert np.linalg.norm(on_face - result.closest_point, axis=1).max() <= tol.EXACT_DISTANCE * diagonal + rounding
    # the normal is a unit vector pointing from the surface to the point (outside) or away (inside)
    np.testing.assert_allclose(np.linalg.norm(result.normal, axis=1), 1.0, atol=1e-5)
    away = np.sign(truth) if signed else 1.0
    facing = np.einsum("ij,ij->i", result.normal, points - result.closest_point) * away
    assert np.all(facing[sure] > 0.0)


def test_a_turned_and_shifted_frame_keeps_the_field_and_answers_for_where_the_mesh_now_is(device: str) -> None:
    vertices, faces = meshes.load("spot")
    vertices = vertices.astype(np.float64)
    field = DistanceField(vertices, faces, depth=5, device=device)
    twin = DistanceField(vertices, faces, depth=5, device=device, rigid="off")
    rng = np.random.default_rng(7)
    before = field.stats()
    for turn, shift in ((_rotation([1, 2, 3], 0.9), [3.0, -1.0, 2.5]), (_rotation([0, 0, 1], np.pi), [0.0, 0.0, 0.0]),
                        (np.eye(3), [1e3, 0.0, -7.0])):
        moved = vertices @ turn.T + np.asarray(shift)
        assert field.update(moved) == twin.update(moved)
        points = _points(moved, faces, rng)
        exact = field.query(points, mode="exact", outputs=ALL_OUTPUTS)
        _assert_true_to(exact, points, moved, faces, signed=True)
        rebuilt = twin.query(points, mode="exact", outputs=ALL_OUTPUTS)
        np.testing.assert_allclose(exact.distance, rebuilt.distance, rtol=0,
                                   atol=2 * tol.EXACT_DISTANCE * oracle.bbox_diagonal(moved))
        # ADF: within a finest cell of the surface, the interpolation's error is below one cell, as rebuilt
        cell = field.info()["domain"]["finest_cell"]
        truth = oracle.signed_distance(points, moved, faces)
        near = np.abs(truth) < cell
        adf = field.query(points[near], mode="adf", outputs=("distance", "normal"))
        assert np.abs(adf.distance - truth[near]).max() < tol.ADF_NEAR_SURFACE * cell
        np.testing.assert_allclose(np.linalg.norm(adf.normal, axis=1), 1.0, atol=1e-4)
        pose = field.info()["pose"]
        np.testing.assert_allclose(pose["rotation"], turn, atol=1e-9)
        np.testing.assert_allclose(pose["translation"], shift, atol=1e-9 * (1 + np.abs(shift).max()))
    stats = field.stats()
    assert stats["rigid_frames"] == 3 and twin.stats()["rigid_frames"] == 0
    # nothing ran on the device for them: the last build's counts and stage times stand
    assert stats["times_ms"] == before["times_ms"] and stats["domain_moves"] == 0
    # the domain is the first frame's cube, carried with the mesh
    fresh = DistanceField(vertices, faces, depth=5, device=device)
    assert field.info()["domain"]["side"] == fresh.info()["domain"]["side"]


def test_a_rigid_frames_points_far_away_and_sent_as_float32_are_answered_as_the_oracle_answers(device: str) -> None:
    vertices, faces = meshes.torus()
    vertices = vertices.astype(np.float64)
    field = DistanceField(vertices, faces, depth=4, device=device)
    moved = vertices @ _rotation([2, -1, 1], 2.0).T + [40.0, -3.0, 12.0]
    field.update(moved)
    assert field.info()["pose"] is not None
    rng = np.random.default_rng(9)
    direction = rng.normal(size=(200, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    far = moved.mean(axis=0) + direction * np.logspace(1, 9, 200)[:, None]  # out to 1e9 sizes: pulled in
    for points in (far, _points(moved, faces, rng, 300).astype(np.float32).astype(np.float64)):
        truth = oracle.signed_distance(points, moved, faces)
        for sent in (points, points.astype(np.float32)):
            result = field.query(sent, mode="exact", outputs=ALL_OUTPUTS)
            assert np.all(np.isfinite(result.distance)) and np.all(np.isfinite(result.closest_point))
            np.testing.assert_allclose(result.distance, truth, rtol=tol.FLOAT32_RELATIVE,
                                       atol=tol.EXACT_DISTANCE * oracle.bbox_diagonal(moved))
    near = _points(moved, faces, rng, 300).astype(np.float32).astype(np.float64)
    _assert_true_to(field.query(near.astype(np.float32), mode="exact", outputs=ALL_OUTPUTS), near, moved, faces,
                    signed=True)


def test_a_slice_and_the_corner_lists_rebuild_a_rigid_frame_in_place_as_rebuilding_it_would(device: str) -> None:
    vertices, faces = meshes.torus()
    field = DistanceField(vertices, faces, depth=5, device=device)
    twin = DistanceField(vertices, faces, depth=5, device=device, rigid="off")
    moved = vertices.astype(np.float64) @ _rotation([1, 0, 1], 0.6).T + [0.25, 0.5, -1.0]
    field.update(moved)
    twin.update(moved)
    assert field.info()["pose"] is not None
    cut = field.slice("z", float(moved[:, 2].mean()), resolution=32)
    assert field.info()["pose"] is None and field.stats()["rigid_rebuilds"] == 1
    np.testing.assert_array_equal(cut.distance, twin.slice("z", float(moved[:, 2].mean()), resolution=32).distance)
    for mine, theirs in zip(field.corner_samples(), twin.corner_samples()):
        np.testing.assert_array_equal(mine, theirs)
    assert field.frame == twin.frame == 1 and field.stats()["rigid_rebuilds"] == 1


def test_frames_that_are_not_rigid_are_rebuilt_and_true_to_the_oracle(device: str) -> None:
    vertices, faces = meshes.sphere()
    vertices = vertices.astype(np.float64)
    field = DistanceField(vertices, faces, depth=5, device=device)
    rng = np.random.default_rng(3)
    diagonal = oracle.bbox_diagonal(vertices)
    nudged = vertices.copy()
    nudged[17] += [1e-4 * diagonal, 0.0, 0.0]  # one vertex a hundred times the tolerance off the motion
    mirrored = vertices * [-1.0, 1.0, 1.0]  # a reflection is no motion: it turns the surface inside out
    stretched = vertices * [1.0, 1.0, 1.0 + 1e-4]
    for frame in (nudged, mirrored, stretched, nudged @ _rotation([0, 1, 0], 0.3).T):
        field.update(frame)
        assert field.info()["pose"] is None
        points = _points(frame, faces, rng, 300)
        _assert_true_to(field.query(points, mode="exact", outputs=ALL_OUTPUTS), points, frame, faces, signed=True)
    assert field.stats()["rigid_frames"] == 0


def test_the_same_frame_again_keeps_the_field_bit_for_bit(device: str) -> None:
    vertices, faces = meshes.box()
    field = DistanceField(vertices, faces, depth=4, device=device)
    points = _points(vertices, faces, np.random.default_rng(5), 200)
    first = field.query(points, mode="exact", outputs=ALL_OUTPUTS)
    for _ in range(2):
        field.update(np.array(vertices))
    again = field.query(points, mode="exact", outputs=ALL_OUTPUTS)
    for name in ALL_OUTPUTS:
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
    assert field.stats()["rigid_frames"] == 2 and field.info()["pose"] is None


def test_rigid_frames_follow_the_last_rebuilt_frame_and_a_band_stays_clamped(device: str) -> None:
    vertices, faces = meshes.load("fandisk")
    vertices = vertices.astype(np.float64)
    diagonal = oracle.bbox_diagonal(vertices)
    band = 0.05 * diagonal
    field = DistanceField(vertices, faces, depth=5, band=band, device=device)
    rng = np.random.default_rng(11)
    bent = vertices + 0.02 * diagonal * np.sin(vertices[:, [1]] * 3.0)  # deformed: rebuilt, the new reference
    frames = [bent @ _rotation([1, 1, 0], 0.4).T + [0.5, 0.0, 0.0], bent, bent + [0.0, -2.0, 0.0]]
    field.update(bent)
    for frame in frames:
        field.update(frame)
        points = _points(frame, faces, rng, 300)
        result = field.query(points, mode="exact", outputs=ALL_OUTPUTS)
        truth = oracle.signed_distance(points, frame, faces)
        np.testing.assert_allclose(result.distance, np.clip(truth, -band, band), rtol=0,
                                   atol=tol.EXACT_DISTANCE * diagonal)
        beyond = np.abs(truth) > band * (1 + 1e-4)
        assert beyond.any() and np.all(result.face[beyond] == -1)
        assert np.all(result.closest_point[beyond] == 0.0) and np.all(result.normal[beyond] == 0.0)
    assert field.stats()["rigid_frames"] == 3


def test_float32_frames_far_from_the_origin_are_rebuilt_where_their_rounding_passes_the_tolerance(device: str) -> None:
    vertices, faces = meshes.sphere()
    field = DistanceField(vertices.astype(np.float32), faces, depth=4, device=device)
    near = (vertices.astype(np.float64) @ _rotation([0, 0, 1], 1.0).T + [2.0, 0.0, 0.0]).astype(np.float32)
    field.update(near)
    assert field.info()["pose"] is not None  # float32 rounding near the origin is far below 1e-6 of the size
    far = (vertices.astype(np.float64) @ _rotation([0, 0, 1], 1.0).T + [1e4, 0.0, 0.0]).astype(np.float32)
    field.update(far)
    assert field.info()["pose"] is None  # at 1e4 sizes float32 rounds by 5e-4 of the size: rebuilt
    points = _points(far.astype(np.float64), faces, np.random.default_rng(2), 200)
    _assert_true_to(field.query(points, mode="exact", outputs=ALL_OUTPUTS), points, far.astype(np.float64), faces,
                    signed=True)


def test_rigid_off_and_a_region_rebuild_every_frame_and_a_bad_mode_is_refused(device: str) -> None:
    vertices, faces = meshes.box()
    moved = vertices + [0.1, 0.0, 0.0]
    region = [[-0.2, -0.2, -0.2], [0.2, 0.2, 0.2]]
    for field in (DistanceField(vertices, faces, depth=3, rigid="off", device=device),
                  DistanceField(vertices, faces, depth=3, region=region, device=device)):
        field.update(moved)
        assert field.info()["rigid"] == "off" and field.stats()["rigid_frames"] == 0
    with pytest.raises(InvalidInputError, match="rigid must be one of"):
        DistanceField(vertices, faces, depth=3, rigid="maybe", device=device)


def test_the_caller_writing_into_its_frame_afterwards_changes_nothing(device: str) -> None:
    vertices, faces = meshes.sphere()
    vertices = vertices.astype(np.float64)
    field = DistanceField(vertices, faces, depth=4, device=device)
    buffer = vertices + [0.3, 0.0, 0.0]
    field.update(buffer)
    buffer += [5.0, 5.0, 5.0]  # a simulation reusing its array
    points = _points(vertices + [0.3, 0.0, 0.0], faces, np.random.default_rng(4), 200)
    _assert_true_to(field.query(points, mode="exact", outputs=ALL_OUTPUTS), points, vertices + [0.3, 0.0, 0.0],
                    faces, signed=True)
    field.slice("x", 0.3, resolution=8)  # rebuilt in place from the frame as it was sent
    _assert_true_to(field.query(points, mode="exact", outputs=ALL_OUTPUTS), points, vertices + [0.3, 0.0, 0.0],
                    faces, signed=True)


def test_a_body_only_moved_rigidly_since_registration_gives_back_what_a_bvh_build_uses(device: str) -> None:
    """Registered, then only turned and shifted (a robot's link, an obstacle): no frame rebuilds, so what only a BVH
    build uses, which a rebuild that keeps the domain frees, stayed for as long as the object lived (4.4 MB for the
    bunny). A run of rigid frames (30 by default, 4 here) now gives it back with the octree's scratch; the queries stay
    exact, and a frame that deforms the body and moves its domain builds the BVH again, exact."""
    vertices, faces = meshes.load("spot")
    vertices = vertices.astype(np.float64)
    rng = np.random.default_rng(43)
    field = DistanceField(vertices, faces, depth=5, device=device)
    field._scratch_kept_frames = 4
    assert field.stats()["memory_bytes"]["rebuild"] > 0
    centre = vertices.mean(axis=0)
    for k in range(1, 5):
        moved = (vertices - centre) @ _rotation([3, 1, 2], 0.2 * k).T + centre + [0.0, 0.04 * k, 0.0]
        field.update(moved)
    stats = field.stats()
    assert stats["rigid_frames"] == 4 and stats["scratch_given_back"] == 1 and stats["memory_bytes"]["rebuild"] == 0
    points = _points(moved, faces, rng)
    _assert_true_to(field.query(points, mode="exact", outputs=ALL_OUTPUTS), points, moved, faces, signed=True)
    thrown = moved * 1.2 + [3.0, 0.0, 0.0]  # deformed (scaled) and out of the domain: a rebuild with a BVH build
    field.update(thrown)
    assert field.stats()["domain_moves"] >= 1
    points = _points(thrown, faces, rng)
    _assert_true_to(field.query(points, mode="exact", outputs=ALL_OUTPUTS), points, thrown, faces, signed=True)
    positions, values, _ = field.corner_samples()
    truth = oracle.signed_distance(positions, thrown, faces)
    assert np.abs(values - truth).max() <= tol.EXACT_DISTANCE * oracle.bbox_diagonal(thrown)


def test_a_long_run_of_rigid_frames_gives_back_the_frame_scratch_until_the_next_rebuild(device: str) -> None:
    """A rigid body's frames rebuild nothing, so after a run of them (30 by default, 4 here) the octree's frame
    scratch is freed: the object holds that much less while it stays rigid, its queries stay exact, and the next
    frame that deforms it allocates the scratch again and is the same field, bit for bit, as that of a twin that
    kept it (on CUDA, its frame run eagerly and then captured again)."""
    vertices, faces = meshes.load("spot")
    vertices = vertices.astype(np.float64)
    rng = np.random.default_rng(41)
    field = DistanceField(vertices, faces, depth=5, device=device)
    twin = DistanceField(vertices, faces, depth=5, device=device)
    field._scratch_kept_frames, twin._scratch_kept_frames = 4, 10**9
    centre = vertices.mean(axis=0)
    for field_of in (field, twin):  # one deforming frame, so that a planned frame (a graph on CUDA) is in hand
        field_of.update(vertices * 1.001)
    held = field.stats()["memory_bytes"]["scratch"]
    for k in range(1, 7):
        moved = (vertices * 1.001 - centre) @ _rotation([1, 2, 3], 0.1 * k).T + centre + [0.05 * k, 0.0, 0.0]
        for field_of in (field, twin):
            field_of.update(moved)
    assert field.stats()["rigid_frames"] == 6 and field.stats()["scratch_given_back"] == 1
    freed = held - field.stats()["memory_bytes"]["scratch"]
    assert freed > 0 and twin.stats()["memory_bytes"]["scratch"] == held
    points = _points(moved, faces, rng)
    result = field.query(points, mode="exact", outputs=ALL_OUTPUTS)
    _assert_true_to(result, points, moved, faces, signed=True)
    for mode in ("adf", "exact"):
        got, expected = field.query(points, mode=mode, outputs=ALL_OUTPUTS), twin.query(points, mode=mode, outputs=ALL_OUTPUTS)
        for name in ALL_OUTPUTS:
            np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))
    # deforming frames: rebuilt, the scratch allocated again, the fields the twin's bit for bit
    captures = field.stats()["graph_captures"]
    for k in range(3):
        bent = moved + 0.01 * np.sin(3.0 * moved[:, [1, 2, 0]]) * (k + 1)
        for field_of in (field, twin):
            field_of.update(bent)
        for got, expected in zip(field.corner_samples(), twin.corner_samples()):
            np.testing.assert_array_equal(got, expected)
        got, expected = field.query(points, outputs=ALL_OUTPUTS), twin.query(points, outputs=ALL_OUTPUTS)
        for name in ALL_OUTPUTS:
            np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))
    assert field.stats()["memory_bytes"] == twin.stats()["memory_bytes"]
    if device.startswith("cuda"):
        assert field.stats()["graph_captures"] > captures
    positions, values, _ = field.corner_samples()
    truth = oracle.signed_distance(positions, bent, faces)
    assert np.abs(values - truth).max() <= tol.EXACT_DISTANCE * oracle.bbox_diagonal(bent)
