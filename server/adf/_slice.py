"""Slices for viewers: the field on an axis-aligned plane, and the octree cells the plane crosses.

Computed only when asked for. The grid is sampled with the ADF interpolation (exact outside the domain); the
cells are every octree cell the plane crosses: the root, the children of every refined node (refined
ones, surface cells at the finest level, and empty leaves), each with its level and whether it is a leaf.
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np
import warp as wp

from badf.server.adf._buffers import DeviceBuffers, HostReadback
from badf.server.adf._geometry import morton3_decode

AXES = ("x", "y", "z")
MAX_SLICE_RESOLUTION = 2048
# cell kinds in the kernel's output
_REFINED, _SURFACE, _EMPTY = 0, 1, 2


@dataclass
class Slice:
    """The field on the plane {axis = position}.

    distance: (rows, cols) float32 signed distance; rows run along the plane's second axis (v), columns
        along its first (u), where (u, v) are the two axes other than `axis` in x, y, z order.
    u_range, v_range: world extent (min, max) the grid covers; grid point (i, j) is at
        u = u_min + (j + 0.5) * (u_max - u_min) / cols, v likewise with rows.
    cell_lower, cell_upper: (K, 3) float32 world corners of the octree cells the plane crosses.
    cell_level: (K,) uint8 octree level of each cell (0 = the domain cube).
    cell_is_leaf: (K,) bool, True for leaves (surface cells at the finest level and empty cells).
    cell_is_empty: (K,) bool, True for empty leaves: cells that hold no surface (nor halo), whose field is
        interpolated from their parent's lattice.
    frame: the frame the slice is of.
    """

    axis: str
    position: float
    distance: np.ndarray
    u_range: tuple[float, float]
    v_range: tuple[float, float]
    cell_lower: np.ndarray
    cell_upper: np.ndarray
    cell_level: np.ndarray
    cell_is_leaf: np.ndarray
    cell_is_empty: np.ndarray
    frame: int


def plane_grid(axis: int, position: float, u_range, v_range, rows: int, cols: int) -> np.ndarray:
    """World points (rows * cols, 3), row-major, at the centres of a rows x cols grid on the plane."""
    u_axis, v_axis = [a for a in range(3) if a != axis]
    u = u_range[0] + (np.arange(cols) + 0.5) * (u_range[1] - u_range[0]) / cols
    v = v_range[0] + (np.arange(rows) + 0.5) * (v_range[1] - v_range[0]) / rows
    points = np.empty((rows, cols, 3), dtype=np.float64)
    points[..., axis] = position
    points[..., u_axis] = u[None, :]
    points[..., v_axis] = v[:, None]
    return points.reshape(-1, 3)


class SliceCells:
    """Device buffers for the cells a plane crosses."""

    def __init__(self, buffers: DeviceBuffers):
        self.buffers = buffers
        self.device = buffers.device
        self.host = HostReadback(self.device)

    def cells(self, node_keys: wp.array, child_mask: wp.array, internal_count: int, level_counts: np.ndarray,
              depth: int, axis: int, local_position: float, side: float, max_level: int):
        """(lower, upper) local corners, levels, leaf and empty flags of the cells crossing the plane;
        `level_counts`: the octree's nodes at each level (those above the finest are its internal nodes).

        The plane is placed on the finest lattice in float64 here, and a cell crosses it when its index along
        the axis holds the plane's finest cell: a plane on a face between two cells is in the upper one only,
        and one on the domain's top face in the top cells (float32 cell bounds rounded both ways)."""
        b = self.buffers
        lattice = (local_position / side + 0.5) * (1 << depth)
        finest = min(math.floor(lattice), (1 << depth) - 1) if 0.0 <= lattice <= (1 << depth) else -1
        candidates = 8 * internal_count + 1  # the root, and every child of a refined node
        capacity = crossing_bound(level_counts, depth, max_level)
        lower = b.ensure("slice.lower", capacity, wp.vec3, headroom=True)
        upper = b.ensure("slice.upper", capacity, wp.vec3, headroom=True)
        level = b.ensure("slice.level", capacity, wp.int32, headroom=True)
        kind = b.ensure("slice.kind", capacity, wp.int32, headroom=True)
        count = b.ensure("slice.count", 1, wp.int32)
        count.zero_()
        wp.launch(
            _crossing_cells,
            dim=candidates,
            inputs=[node_keys, child_mask, internal_count, depth, axis, finest, side, max_level, lower.shape[0]],
            outputs=[lower, upper, level, kind, count],
            device=self.device,
        )
        n = self.host.read(count, 0)
        if n > lower.shape[0]:  # crossing_bound holds for any octree: only level_counts of another frame pass it
            raise RuntimeError(f"a slice crossed {n} cells, more than the {lower.shape[0]} its levels allow")
        if n == 0:  # a plane outside the domain (no zero-length copies from the device)
            none = np.zeros(0, dtype=bool)
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.uint8), none, none
        # only the cells listed come back (on CUDA the buffers were copied whole before: 7.7 MB for the bunny at 7)
        kinds = kind[:n].numpy()
        return (lower[:n].numpy().copy(), upper[:n].numpy().copy(), level[:n].numpy().astype(np.uint8),
                kinds != _REFINED, kinds == _EMPTY)


def crossing_bound(level_counts: np.ndarray, depth: int, max_level: int) -> int:
    """How many cells an axis-aligned plane can cross, at most: the root, and at each level L down to max_level the
    fewer of the children of the refined nodes above (8 each) and the 4^L cells of the one layer of the grid at L
    that holds the plane. The bunny at depth 7 has 192,200 children of refined nodes, and a plane crosses at most
    21,844 of them."""
    bound = 1
    for lvl in range(1, min(depth, max_level) + 1):
        bound += min(8 * int(level_counts[lvl - 1]), 4**lvl)
    return bound


@wp.kernel(enable_backward=False)
def _crossing_cells(
    node_keys: wp.array(dtype=wp.int64),
    child_mask: wp.array(dtype=wp.int32),
    internal_count: int,
    depth: int,
    axis: int,
    finest: int,
    side: float,
    max_level: int,
    capacity: int,
    out_lower: wp.array(dtype=wp.vec3),
    out_upper: wp.array(dtype=wp.vec3),
    out_level: wp.array(dtype=wp.int32),
    out_kind: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    # item 0 is the root; item 1 + 8 n + o is child o of internal node n
    i = wp.tid()
    level = int(0)
    cell = wp.vec3i(0, 0, 0)
    kind = int(0)  # refined; 1 surface leaf, 2 empty leaf
    if i > 0:
        node = (i - 1) // 8
        octant = (i - 1) % 8
        key = node_keys[node]
        parent_level = int(key >> wp.int64(32))
        parent = morton3_decode(key & wp.int64(0xFFFFFFFF))
        level = parent_level + 1
        cell = wp.vec3i(2 * parent[0] + ((octant >> 2) & 1), 2 * parent[1] + ((octant >> 1) & 1),
                        2 * parent[2] + (octant & 1))
        if (child_mask[node] >> octant) & 1 == 0:
            kind = 2
        elif level == depth:
            kind = 1
    # the plane lies in finest cell `finest` along the axis (-1: outside the domain)
    if level > max_level or finest < 0 or cell[axis] != (finest >> (depth - level)):
        return
    size = side / float(1 << level)
    origin = wp.vec3(-0.5 * side)
    lower = origin + wp.vec3(float(cell[0]), float(cell[1]), float(cell[2])) * size
    upper = lower + wp.vec3(size)
    slot = wp.atomic_add(count, 0, 1)
    if slot >= capacity:
        return
    out_lower[slot] = lower
    out_upper[slot] = upper
    out_level[slot] = level
    out_kind[slot] = kind
