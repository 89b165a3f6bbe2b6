"""The truth the tests and benchmarks compare against: float64 brute force over every (point, triangle) pair.

Slow on purpose and simple enough to check by eye. Sign convention as in the engine: negative inside.
Inside/outside comes from the generalised winding number (Jacobson et al. 2013), |w| > 1/2 meaning inside,
so a closed mesh given inside out gets the same answer as the right way round.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Pairs (point, triangle) evaluated per numpy batch; bounds the oracle's memory to a few hundred MB.
_PAIRS_PER_BATCH = 1_000_000


@dataclass(frozen=True)
class Nearest:
    distance: np.ndarray  # (P,) unsigned distance to the mesh, float64
    face: np.ndarray  # (P,) index of a nearest face
    closest_point: np.ndarray  # (P, 3) the nearest point on that face


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", u, v)


def _closest_on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    length_sq = _dot(ab, ab)
    t = np.where(length_sq > 0.0, _dot(p - a, ab) / np.where(length_sq > 0.0, length_sq, 1.0), 0.0)
    return a + np.clip(t, 0.0, 1.0)[..., None] * ab


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point on triangle (a, b, c) to p, broadcasting over leading axes; exact for degenerate ones.

    The candidates are the three edges (as segments) and, when the projection of p falls inside a triangle
    of non-zero area, that projection; the nearest candidate wins.
    """
    candidates = [_closest_on_segment(p, a, b), _closest_on_segment(p, b, c), _closest_on_segment(p, c, a)]
    n = np.cross(b - a, c - a)
    n_sq = _dot(n, n)
    safe = np.where(n_sq > 0.0, n_sq, 1.0)
    q = p - (_dot(p - a, n) / safe)[..., None] * n
    inside = (
        (n_sq > 0.0)
        & (_dot(np.cross(b - a, q - a), n) >= 0.0)
        & (_dot(np.cross(c - b, q - b), n) >= 0.0)
        & (_dot(np.cross(a - c, q - c), n) >= 0.0)
    )
    best = candidates[0]
    best_sq = _dot(p - best, p - best)
    for candidate in candidates[1:] + [np.where(inside[..., None], q, candidates[0])]:
        d_sq = _dot(p - candidate, p - candidate)
        better = d_sq < best_sq
        best = np.where(better[..., None], candidate, best)
        best_sq = np.where(better, d_sq, best_sq)
    return best


def _batches(point_count: int, face_count: int):
    step = max(1, _PAIRS_PER_BATCH // max(face_count, 1))
    for start in range(0, point_count, step):
        yield slice(start, min(point_count, start + step))


def nearest(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *, prune: bool = True) -> Nearest:
    """Unsigned distance, a nearest face and the closest point for each point, in float64.

    With prune=True only the triangles that could be nearest are evaluated: a triangle's centroid lies on
    it, so the nearest centroid bounds the distance from above, and no point of a triangle is closer than
    (distance to its centroid - its circumradius about the centroid). The bound is exact, not a heuristic;
    tests/test_oracle.py checks the two paths agree.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    distance = np.empty(len(points))
    face = np.empty(len(points), dtype=np.int64)
    closest = np.empty((len(points), 3))
    if not prune:
        a, b, c = tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]
        for rows in _batches(len(points), len(tri)):
            p = points[rows, None, :]
            q = closest_points_on_triangles(p, a, b, c)
            d_sq = _dot(p - q, p - q)
            best = np.argmin(d_sq, axis=1)
            idx = np.arange(len(best))
            distance[rows] = np.sqrt(d_sq[idx, best])
            face[rows] = best
            closest[rows] = q[idx, best]
        return Nearest(distance, face, closest)
    centroid = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroid[:, None, :], axis=2).max(axis=1)
    for rows in _batches(len(points), len(tri)):
        p = points[rows]
        to_centroid = np.linalg.norm(p[:, None, :] - centroid[None, :, :], axis=2)
        upper = to_centroid.min(axis=1)
        # keep every triangle whose lower bound does not exceed the upper bound (with rounding room)
        slack = 1e-9 * (upper + radius.max())
        point_idx, tri_idx = np.nonzero(to_centroid - radius[None, :] <= (upper + slack)[:, None])
        q = closest_points_on_triangles(p[point_idx], tri[tri_idx, 0], tri[tri_idx, 1], tri[tri_idx, 2])
        d_sq = _dot(p[point_idx] - q, p[point_idx] - q)
        order = np.lexsort((d_sq, point_idx))  # by point, then distance
        first = order[np.r_[True, point_idx[order][1:] != point_idx[order][:-1]]]
        distance[rows] = np.sqrt(d_sq[first])
        face[rows] = tri_idx[first]
        closest[rows] = q[first]
    return Nearest(distance, face, closest)


def winding_number(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding number of each point: sum of signed solid angles / 4 pi (Van Oosterom-Strackee)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    w = np.empty(len(points))
    for rows in _batches(len(points), len(tri)):
        a = tri[None, :, 0] - points[rows, None, :]
        b = tri[None, :, 1] - points[rows, None, :]
        c = tri[None, :, 2] - points[rows, None, :]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = _dot(a, np.cross(b, c))
        denominator = la * lb * lc + _dot(a, b) * lc + _dot(a, c) * lb + _dot(b, c) * la
        w[rows] = np.sum(2.0 * np.arctan2(det, denominator), axis=1) / (4.0 * np.pi)
    return w


def signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *, signed: bool = True) -> np.ndarray:
    """Signed distance (negative inside, by winding number) or, with signed=False, the unsigned distance."""
    d = nearest(points, vertices, faces).distance
    if not signed:
        return d
    inside = np.abs(winding_number(points, vertices, faces)) > 0.5
    return np.where(inside, -d, d)


# Points of a benchmark checked against the oracle, beside its times: a sample, as the oracle takes seconds
# per thousand points on a mesh of 70K triangles.
ORACLE_SAMPLE = 1000


def errors_against(values: np.ndarray, truth: np.ndarray, vertices: np.ndarray) -> dict:
    """Largest and mean |values - truth| in bounding-box diagonals of `vertices`, over every value: `values`
    may stack several answers (P,) to the same P points, `truth` the oracle's (P,) answers to them."""
    error = np.abs(np.asarray(values, np.float64) - truth) / bbox_diagonal(vertices)
    return {"points": int(np.size(truth)), "max_error_diag": float(error.max()), "mean_error_diag": float(error.mean())}


def bbox_diagonal(vertices: np.ndarray) -> float:
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
