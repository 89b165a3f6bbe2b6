"""Geometry on a slice plane: where the image goes, the zero contour, the cells' outlines, the leaf corners.

Numpy only. A slice (badf.protocol.SliceReply) is the plane `axis` = `position`; its axes (u, v) are the
two others in x, y, z order; its grid's rows run along v and its columns along u, sample (i, j) at the
centre of its cell of the `extent`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from badf.protocol import AXES, CELL_LEAF

# Rotations (w, x, y, z) of viser's image plane (columns along its local x, rows along its local y, with
# row 0 at -y) onto a slice plane: local x to the u axis, local y to the v axis.
_IMAGE_ROTATIONS = {
    "x": (0.5, 0.5, 0.5, 0.5),  # local x, y, z -> world y, z, x
    "y": (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0),  # local x, y, z -> world x, z, -y
    "z": (1.0, 0.0, 0.0, 0.0),
}
# A corner's probe point lies this fraction of the way from the corner towards its leaf's centre: inside
# that leaf, where the field interpolates to the corner's own sample.
_PROBE_INSET = 1e-3


@dataclass(frozen=True)
class PlaneFrame:
    """The plane of a slice: `axis` = `position`, covering `extent` ((u_min, v_min), (u_max, v_max))."""

    axis: str
    position: float
    extent: tuple[tuple[float, float], tuple[float, float]]

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise ValueError(f"axis must be one of {', '.join(AXES)}, got {self.axis!r}")
        (u0, v0), (u1, v1) = self.extent
        if not (u1 > u0 and v1 > v0):
            raise ValueError(f"extent must be ((u_min, v_min), (u_max, v_max)) with max > min, got {self.extent}")

    @property
    def axis_index(self) -> int:
        return AXES.index(self.axis)

    @property
    def uv_indices(self) -> tuple[int, int]:
        u, v = (a for a in range(3) if a != self.axis_index)
        return u, v

    def to_world(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(..., 3) float32 world points of plane coordinates u, v (same shapes)."""
        u_index, v_index = self.uv_indices
        points = np.empty(np.shape(u) + (3,), dtype=np.float32)
        points[..., self.axis_index] = self.position
        points[..., u_index] = u
        points[..., v_index] = v
        return points

    def image_pose(self) -> tuple[tuple[float, float, float, float], np.ndarray, float, float]:
        """(wxyz, centre, width, height) that lay an image of the grid (row 0 first) over the extent."""
        (u0, v0), (u1, v1) = self.extent
        centre = self.to_world(np.float32((u0 + u1) / 2), np.float32((v0 + v1) / 2))
        return _IMAGE_ROTATIONS[self.axis], centre, u1 - u0, v1 - v0


def zero_contour(grid: np.ndarray, frame: PlaneFrame) -> np.ndarray:
    """(S, 2, 3) float32 world segments where the sampled signed distance changes sign (marching squares
    on the sample centres, linear along each edge; a saddle is split by the sign of the square's mean)."""
    grid = np.asarray(grid, dtype=np.float32)
    if grid.ndim != 2 or min(grid.shape) < 2:
        return np.zeros((0, 2, 3), np.float32)
    a, b = grid[:-1, :-1], grid[:-1, 1:]  # corners of each square: a (i, j), b (i, j+1),
    c, d = grid[1:, 1:], grid[1:, :-1]  # c (i+1, j+1), d (i+1, j)
    rows, cols = np.meshgrid(np.arange(a.shape[0], dtype=np.float32), np.arange(a.shape[1], dtype=np.float32),
                             indexing="ij")  # fmt: skip
    # The four edges, each as (from value, to value, from (row, col), step (row, col)).
    edges = ((a, b, (rows, cols), (0, 1)), (b, c, (rows, cols + 1), (1, 0)),
             (d, c, (rows + 1, cols), (0, 1)), (a, d, (rows, cols), (1, 0)))  # fmt: skip
    crosses = np.stack([(p < 0) != (q < 0) for p, q, _, _ in edges], axis=-1)  # (H-1, W-1, 4)
    points = np.empty(crosses.shape + (2,), dtype=np.float32)  # (row, col) of each edge's crossing
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, (p, q, (row, col), (step_row, step_col)) in enumerate(edges):
            t = np.where(crosses[..., k], p / (p - q), 0.0)
            points[..., k, 0] = row + step_row * t
            points[..., k, 1] = col + step_col * t
    count = crosses.sum(axis=-1)
    two = count == 2
    first_two = np.argsort(~crosses[two], axis=-1, kind="stable")[:, :2]
    pairs = [np.take_along_axis(points[two], first_two[:, :, None], axis=1)]
    four = count == 4
    if four.any():
        # Corner a's sign reaches the centre: the lines cut off corners b (edges 0, 1) and d (2, 3);
        # otherwise they cut off a (3, 0) and c (1, 2).
        centre_like_a = ((a + b + c + d)[four] < 0) == (a[four] < 0)
        saddle = points[four]
        order = np.where(centre_like_a[:, None], np.array([0, 1, 2, 3]), np.array([3, 0, 1, 2]))
        ordered = np.take_along_axis(saddle, order[:, :, None], axis=1)
        pairs.append(ordered.reshape(-1, 2, 2))
    index_space = np.concatenate(pairs, axis=0)  # (S, 2, (row, col))
    (u0, v0), (u1, v1) = frame.extent
    height, width = grid.shape
    u = u0 + (index_space[..., 1] + 0.5) * ((u1 - u0) / width)
    v = v0 + (index_space[..., 0] + 0.5) * ((v1 - v0) / height)
    return frame.to_world(u, v)


def cell_outlines(cell_boxes: np.ndarray, frame: PlaneFrame) -> np.ndarray:
    """(4 K, 2, 3) float32 segments: the rectangle where each cell box (K, 2, 3) meets the plane."""
    boxes = np.asarray(cell_boxes, dtype=np.float32)
    u_index, v_index = frame.uv_indices
    u_lo, u_hi = boxes[:, 0, u_index], boxes[:, 1, u_index]
    v_lo, v_hi = boxes[:, 0, v_index], boxes[:, 1, v_index]
    corners_u = np.stack([u_lo, u_hi, u_hi, u_lo], axis=1)  # (K, 4), counter-clockwise
    corners_v = np.stack([v_lo, v_lo, v_hi, v_hi], axis=1)
    corners = frame.to_world(corners_u, corners_v)  # (K, 4, 3)
    return np.stack([corners, np.roll(corners, -1, axis=1)], axis=2).reshape(-1, 2, 3)


def on_both_sides(segments: np.ndarray, frame: PlaneFrame, offset: float) -> np.ndarray:
    """The segments twice, lifted `offset` off the plane to either side, so that they show over the slice
    image (which they would otherwise fight for depth) from wherever it is seen."""
    lifted = np.concatenate([segments, segments], axis=0)
    lifted[: len(segments), :, frame.axis_index] += offset
    lifted[len(segments) :, :, frame.axis_index] -= offset
    return lifted


def leaf_corners(cell_boxes: np.ndarray, cell_flags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sample points of the leaf cells among the cells a plane crosses: each leaf's 8 corners (every
    leaf's field is interpolated from them), de-duplicated. Returns (corners (C, 3), probes (C, 3)) float32;
    a probe lies just inside one leaf that owns its corner, where the field is that corner's sample."""
    boxes = np.asarray(cell_boxes, dtype=np.float32)[(np.asarray(cell_flags) & CELL_LEAF) > 0]
    if len(boxes) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    lower, upper = boxes[:, 0].astype(np.float64), boxes[:, 1].astype(np.float64)
    bits = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], dtype=np.float64)  # (8, 3)
    corners = lower[:, None, :] + bits[None] * (upper - lower)[:, None, :]  # (L, 8, 3)
    centres = np.repeat(((lower + upper) / 2)[:, None, :], 8, axis=1)
    finest = float((upper - lower).min())
    lattice = np.rint((corners.reshape(-1, 3) - lower.min(axis=0)) / finest).astype(np.int64)
    _, first = np.unique(lattice, axis=0, return_index=True)
    corners, centres = corners.reshape(-1, 3)[first], centres.reshape(-1, 3)[first]
    probes = corners + _PROBE_INSET * (centres - corners)
    return corners.astype(np.float32), probes.astype(np.float32)
