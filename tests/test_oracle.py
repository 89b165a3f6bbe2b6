"""The oracle checks itself: the pruned search equals the plain brute force, and known answers hold."""

import numpy as np

import oracle


def test_pruned_search_equals_brute_force():
    rng = np.random.default_rng(7)
    vertices = rng.normal(size=(60, 3))
    faces = rng.integers(0, 60, size=(120, 3))
    faces[:5, 1] = faces[:5, 0]  # some degenerate triangles too
    points = rng.normal(scale=2.0, size=(300, 3))
    pruned = oracle.nearest(points, vertices, faces)
    plain = oracle.nearest(points, vertices, faces, prune=False)
    np.testing.assert_allclose(pruned.distance, plain.distance, rtol=0, atol=1e-12)


def test_known_distances_and_winding_numbers():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward-facing tetrahedron
    points = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, -1.0], [3.0, 0.0, 0.0]])
    near = oracle.nearest(points, vertices, faces)
    np.testing.assert_allclose(near.distance, [0.1, 1.0, 2.0], atol=1e-12)
    w = oracle.winding_number(points, vertices, faces)
    np.testing.assert_allclose(w, [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(oracle.signed_distance(points, vertices, faces), [-0.1, 1.0, 2.0], atol=1e-12)


def test_degenerate_triangle_is_its_edges():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], dtype=np.float64)  # collinear
    near = oracle.nearest(np.array([[1.5, 1.0, 0.0], [3.0, 0.0, 0.0]]), vertices, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(near.distance, [1.0, 1.0], atol=1e-12)
