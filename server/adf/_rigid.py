"""Rigid frames: a frame that moves the whole mesh as one body is answered by moving the queries instead.

A robot's links, a tool, the static parts of a scene: their frames are the registered mesh turned and shifted.
The distance to R x + t of a surface is the distance of R^T (p - t) to the surface itself, so such a frame keeps
the field built for the reference frame (the last one rebuilt) and holds only the pose (R, t) from it. Queries
are moved into the reference frame, their closest points and normals back out. Nothing runs on the device.

A frame is taken as rigid where one proper rotation and translation carry every used vertex of the reference
frame to within RIGID_TOLERANCE of the bounding box's diagonal of where the frame puts it: the answers are then
those of a surface that far from the frame's at most, against the 1e-5 of the diagonal that exact queries keep.
The test first fits the pose to a few spread vertices (Kabsch's method) and checks them, which turns a deforming
frame away cheaply, and only then checks every vertex.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from badf.server.adf._tolerances import RIGID_SAMPLE, RIGID_TOLERANCE

RIGID_MODES: tuple[str, ...] = ("auto", "off")

# rows checked at a time in the full test, so a frame that fails far in stops early and the temporary stays small
_CHECK_ROWS = 16384


@dataclass(frozen=True)
class Pose:
    """A proper rigid motion x -> rotation @ x + translation, from the reference frame to the current one."""

    rotation: np.ndarray  # (3, 3) float64, orthonormal, determinant +1
    translation: np.ndarray  # (3,) float64

    def vectors_to_world(self, vectors: np.ndarray) -> np.ndarray:
        """Directions of the reference frame turned with the current one, float32."""
        return _turn(self.rotation, vectors.astype(np.float64)).astype(np.float32)

    def as_dict(self) -> dict:
        return {"rotation": self.rotation.tolist(), "translation": self.translation.tolist()}


class RigidTest:
    """Which vertices a frame's pose is fitted to first, and the test of a frame against the reference frame."""

    def __init__(self, vertices: np.ndarray, used: np.ndarray | None):
        """vertices: the first frame; used: the indices of the vertices faces use (None: all)."""
        self._used = used
        points = vertices if used is None else vertices[used]
        count = len(points)
        # spread vertices, and each axis's extremes in the first frame, which pin the rotation however the
        # vertices are ordered
        spread = np.linspace(0, count - 1, min(count, RIGID_SAMPLE)).astype(np.int64)
        extremes = np.concatenate([points.argmin(axis=0), points.argmax(axis=0)])
        chosen = np.unique(np.concatenate([spread, extremes]))
        self._sample = chosen if used is None else used[chosen]

    def pose(self, reference: np.ndarray, frame: np.ndarray, tolerance: float) -> Pose | None:
        """The rigid motion that carries the reference frame's used vertices to this frame's within `tolerance`
        (every coordinate), or None. A frame the same as the reference, bit for bit, is the identity pose."""
        before = reference[self._sample].astype(np.float64)
        after = frame[self._sample].astype(np.float64)
        if np.array_equal(before, after) and np.array_equal(self._rows(reference), self._rows(frame)):
            return Pose(np.eye(3), np.zeros(3))
        if not _lengths_kept(before, after, tolerance):
            return None
        pose = _fit(before, after)
        if pose is None or not _within(before, after, pose, tolerance):
            return None
        count = len(reference) if self._used is None else len(self._used)
        for start in range(0, count, _CHECK_ROWS):
            rows = slice(start, start + _CHECK_ROWS)
            if not _within(self._rows(reference, rows), self._rows(frame, rows), pose, tolerance):
                return None
        return pose

    def _rows(self, vertices: np.ndarray, rows: slice = slice(None)) -> np.ndarray:
        """The used vertices' rows `rows`, in their own precision."""
        return vertices[rows] if self._used is None else vertices[self._used[rows]]


def _turn(matrix: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """matrix @ each row of (P, 3) rows, as (P, 3) float64. numpy's (P, 3) @ (3, 3) takes a slow path (3.9 ms for
    65,536 points on 2 cores); the (3, 3) @ (3, P) product of the rows' transpose runs as one BLAS call (0.4 ms)."""
    return (matrix @ np.ascontiguousarray(rows.T)).T


def _lengths_kept(before: np.ndarray, after: np.ndarray, tolerance: float) -> bool:
    """Whether the distances between successive sample vertices stayed within what moving each vertex by
    `tolerance` per coordinate allows (2 sqrt(3) tolerance): a rigid motion keeps them, and most deforming frames
    fail here, before the fit."""
    change = np.abs(np.linalg.norm(np.diff(before, axis=0), axis=1) - np.linalg.norm(np.diff(after, axis=0), axis=1))
    return bool(change.max(initial=0.0) <= 2.0 * math.sqrt(3.0) * tolerance)


def _within(reference: np.ndarray, frame: np.ndarray, pose: Pose, tolerance: float) -> bool:
    """Whether the pose carries every reference row to the frame's within `tolerance` per coordinate."""
    moved = _turn(pose.rotation, reference)
    moved += pose.translation
    moved -= frame
    return bool(np.abs(moved, out=moved).max() <= tolerance)


def _fit(reference: np.ndarray, frame: np.ndarray) -> Pose | None:
    """The least-squares proper rotation and translation from reference to frame points (Kabsch, 1976), or None
    where the SVD does not converge. For points on a line the rotation about it is arbitrary, which the check on
    every vertex allows: any motion that carries every vertex there is as good."""
    reference_centre, frame_centre = reference.mean(axis=0), frame.mean(axis=0)
    covariance = (reference - reference_centre).T @ (frame - frame_centre)
    if not np.all(np.isfinite(covariance)):
        return None
    try:
        u, _, vt = np.linalg.svd(covariance)
    except np.linalg.LinAlgError:
        return None
    flip = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, flip]) @ u.T
    return Pose(rotation, frame_centre - rotation @ reference_centre)
