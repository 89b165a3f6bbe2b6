"""The octree: surface cells, their radix tree, the paper's Algorithm 1, and the de-duplicated corners.

Stages, each count-allocate-fill with one host read-back of a total:
1. Surface cells at the finest level: every cell a triangle overlaps ("surface", the default), or the cell
   holding its centroid ("centroid", the paper's rule), grown by `halo` cells in every direction (default 1:
   then any point within one finest cell of the surface is interpolated in a finest cell, whose corners
   are exact, rather than in a large empty cell across a coarse cell boundary). Sorted and made unique.
2. Karras's radix tree over those cell keys; the paper's Algorithm 1 turns each tree edge whose common
   prefix crosses a multiple of 3 bits into the octree nodes between the two ends, so every node is made
   exactly once and in parallel. The nodes are sorted by (level, Morton code).
3. Links: each internal node gets an 8-bit child mask and the index of its first child; children of one
   node are contiguous. A point is located by walking the masks from the root.
4. Corners: each internal node names the 27 lattice points of its 2x2x2 children; they are sorted by
   Morton code and made unique, and every node keeps the index of each of its 27 points.
Every node above the finest level holds surface, so every internal node is refined into 8 children;
children that hold no surface are empty leaves, whose corners come from their parent's 27 points.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import warp as wp

from badf.server.adf._buffers import DeviceBuffers
from badf.server.adf._bvh import link_radix_tree
from badf.server.adf._geometry import KEY_TOP_BIT, morton3, morton3_decode, popcount, quantize, triangle_overlaps_cube
from badf.server.adf._tolerances import CELL_OVERLAP_SLACK

Refinement = Literal["surface", "centroid"]

LEVEL_SHIFT = 32  # octree node keys: level << 32 | Morton code of the node at its level
_LEVEL_SHIFT = wp.constant(LEVEL_SHIFT)
_CODE_MASK = wp.constant(wp.int64(0xFFFFFFFF))
_SLACK = wp.constant(CELL_OVERLAP_SLACK)


@wp.struct
class OctreeView:
    """What point location and interpolation read of an octree."""

    depth: int
    origin: wp.vec3  # domain corner (local coordinates)
    cell: float  # finest cell size
    child_mask: wp.array(dtype=wp.int32)  # (internal,) bit o set when child o holds surface
    first_child: wp.array(dtype=wp.int32)  # (internal,) node index of the first child present
    corner_slot: wp.array(dtype=wp.int32)  # (internal * 27,) unique-corner index of each lattice point


class Octree:
    """Owns one object's octree buffers; `build` remakes the tree for the current vertices."""

    def __init__(self, depth: int, refine: Refinement, halo: int, buffers: DeviceBuffers):
        self.depth = depth
        self.refine = refine
        self.halo = halo
        self.buffers = buffers
        self.device = buffers.device
        self.host = _HostCounts(self.device)
        # filled by build()
        self.surface_cell_count = 0  # unique finest cells holding surface
        self.node_count = 0
        self.internal_count = 0
        self.level_counts = np.zeros(depth + 1, dtype=np.int64)
        self.corner_candidate_count = 0
        self.corner_count = 0
        self.corner_keys: wp.array | None = None
        self.corner_slot: wp.array | None = None
        self.child_mask: wp.array | None = None
        self.first_child: wp.array | None = None
        self.node_keys: wp.array | None = None

    def build(self, vertices: wp.array, faces: wp.array, face_count: int, origin: wp.vec3, side: float, clock) -> None:
        with clock.stage("surface_cells"):
            cell_keys = self._surface_cells(vertices, faces, face_count, origin, side)
        with clock.stage("octree"):
            self._octree_nodes(cell_keys)
            self._link_children()
        with clock.stage("corners"):
            self._corners()

    def view(self, origin: wp.vec3, side: float) -> OctreeView:
        v = OctreeView()
        v.depth = self.depth
        v.origin = origin
        v.cell = side / float(1 << self.depth)
        v.child_mask = self.child_mask
        v.first_child = self.first_child
        v.corner_slot = self.corner_slot
        return v

    # -- stage 1: surface cells -------------------------------------------------------------------------
    def _surface_cells(self, vertices, faces, face_count: int, origin: wp.vec3, side: float) -> wp.array:
        b, d = self.buffers, self.depth
        resolution = 1 << d
        cell = side / resolution
        shift = KEY_TOP_BIT - 3 * d
        if self.refine == "surface":
            counts = b.ensure("oct.tri_cell_counts", face_count, wp.int32)
            offsets = b.ensure("oct.tri_cell_offsets", face_count, wp.int32)
            keys = b.ensure("oct.cell_keys", 1, wp.int64)
            args = [vertices, faces, origin, cell, resolution, shift]
            wp.launch(_surface_cells, dim=face_count, inputs=[*args, 0, offsets], outputs=[counts, keys],
                      device=self.device)
            wp.utils.array_scan(counts[:face_count], offsets[:face_count], inclusive=False)
            total = self.host.read_sum(counts, offsets, face_count - 1)
            keys = b.ensure("oct.cell_keys", 2 * total, wp.int64)
            wp.launch(_surface_cells, dim=face_count, inputs=[*args, 1, offsets], outputs=[counts, keys],
                      device=self.device)
        else:
            total = face_count
            keys = b.ensure("oct.cell_keys", 2 * total, wp.int64)
            wp.launch(_centroid_cells, dim=face_count, inputs=[vertices, faces, origin, cell, resolution, shift],
                      outputs=[keys], device=self.device)
        values = b.ensure("oct.cell_values", 2 * total, wp.int32)
        wp.utils.radix_sort_pairs(keys, values, total, begin_bit=shift, end_bit=KEY_TOP_BIT)
        cells, count = self._unique(keys, total, "oct.cells")
        if self.halo > 0:
            width = 2 * self.halo + 1
            grown = count * width**3
            keys = b.ensure("oct.halo_keys", 2 * grown, wp.int64)
            values = b.ensure("oct.halo_values", 2 * grown, wp.int32)
            wp.launch(_grow_cells, dim=grown, inputs=[cells, self.halo, resolution, shift], outputs=[keys],
                      device=self.device)
            wp.utils.radix_sort_pairs(keys, values, grown, begin_bit=shift, end_bit=KEY_TOP_BIT)
            cells, count = self._unique(keys, grown, "oct.halo")
        self.surface_cell_count = count
        return cells

    def _unique(self, sorted_keys: wp.array, count: int, name: str) -> tuple[wp.array, int]:
        """Compact sorted int64 keys to their distinct values; returns (array, distinct count)."""
        b = self.buffers
        flags = b.ensure(name + ".flags", count, wp.int32)
        scan = b.ensure(name + ".scan", count, wp.int32)
        wp.launch(_mark_first_of_run, dim=count, inputs=[sorted_keys], outputs=[flags], device=self.device)
        wp.utils.array_scan(flags[:count], scan[:count], inclusive=True)
        distinct = self.host.read(scan, count - 1)
        out = b.ensure(name + ".unique", distinct, wp.int64)
        wp.launch(_compact_runs, dim=count, inputs=[sorted_keys, flags, scan], outputs=[out], device=self.device)
        return out, distinct

    # -- stage 2: Algorithm 1 over the radix tree of the cells ---------------------------------------------
    def _octree_nodes(self, cell_keys: wp.array) -> None:
        b, d = self.buffers, self.depth
        n = self.surface_cell_count
        tree_nodes = 2 * n - 1
        parent = b.ensure("oct.tree.parent", tree_nodes, wp.int32)
        left = b.ensure("oct.tree.left", max(n - 1, 1), wp.int32)
        right = b.ensure("oct.tree.right", max(n - 1, 1), wp.int32)
        first = b.ensure("oct.tree.first", max(n - 1, 1), wp.int32)
        prefix = b.ensure("oct.tree.prefix", max(n - 1, 1), wp.int32)
        link_radix_tree(cell_keys, n, parent, left, right, first, prefix)

        counts = b.ensure("oct.edge_counts", tree_nodes, wp.int32)
        offsets = b.ensure("oct.edge_offsets", tree_nodes, wp.int32)
        level_counts = b.ensure("oct.level_counts", d + 1, wp.int32)
        level_counts.zero_()
        wp.launch(_count_octree_nodes, dim=tree_nodes, inputs=[parent, prefix, n - 1, d],
                  outputs=[counts, level_counts], device=self.device)
        wp.utils.array_scan(counts[:tree_nodes], offsets[:tree_nodes], inclusive=False)
        self.level_counts = self.host.read_array(level_counts, d + 1).astype(np.int64)
        total = int(self.level_counts.sum())
        node_keys = b.ensure("oct.node_keys", 2 * total, wp.int64)
        scratch = b.ensure("oct.node_values", 2 * total, wp.int32)
        wp.launch(_fill_octree_nodes, dim=tree_nodes, inputs=[cell_keys, parent, prefix, first, n - 1, d, offsets],
                  outputs=[node_keys], device=self.device)
        wp.utils.radix_sort_pairs(node_keys, scratch, total, end_bit=LEVEL_SHIFT + 4)
        self.node_keys = node_keys
        self.node_count = total
        self.internal_count = total - int(self.level_counts[d])

    # -- stage 3: child masks and first children ----------------------------------------------------------
    def _link_children(self) -> None:
        b = self.buffers
        total, internal = self.node_count, self.internal_count
        flags = b.ensure("oct.first_child_flags", total, wp.int32)
        scan = b.ensure("oct.first_child_scan", total, wp.int32)
        self.child_mask = b.ensure("oct.child_mask", internal, wp.int32)
        self.first_child = b.ensure("oct.first_child", internal, wp.int32)
        self.child_mask.zero_()
        wp.launch(_mark_first_children, dim=total, inputs=[self.node_keys], outputs=[flags], device=self.device)
        wp.utils.array_scan(flags[:total], scan[:total], inclusive=True)
        if total > 1:
            wp.launch(_link_children, dim=total - 1, inputs=[self.node_keys, flags, scan],
                      outputs=[self.child_mask, self.first_child], device=self.device)

    # -- stage 4: corners ---------------------------------------------------------------------------------
    def _corners(self) -> None:
        b, d = self.buffers, self.depth
        candidates = 27 * self.internal_count
        keys = b.ensure("oct.corner_candidate_keys", 2 * candidates, wp.int64)
        slots = b.ensure("oct.corner_candidate_slots", 2 * candidates, wp.int32)
        wp.launch(_corner_candidates, dim=candidates, inputs=[self.node_keys, d], outputs=[keys, slots],
                  device=self.device)
        wp.utils.radix_sort_pairs(keys, slots, candidates, end_bit=3 * (d + 1))
        flags = b.ensure("oct.corner_flags", candidates, wp.int32)
        scan = b.ensure("oct.corner_scan", candidates, wp.int32)
        wp.launch(_mark_first_of_run, dim=candidates, inputs=[keys], outputs=[flags], device=self.device)
        wp.utils.array_scan(flags[:candidates], scan[:candidates], inclusive=True)
        self.corner_count = self.host.read(scan, candidates - 1)
        self.corner_candidate_count = candidates
        self.corner_slot = b.ensure("oct.corner_slot", candidates, wp.int32)
        self.corner_keys = b.ensure("oct.corner_keys", self.corner_count, wp.int64)
        wp.launch(_number_corners, dim=candidates, inputs=[keys, slots, flags, scan],
                  outputs=[self.corner_slot, self.corner_keys], device=self.device)


class _HostCounts:
    """Reads a few integers back from the device through one small pinned buffer (no allocation per frame)."""

    def __init__(self, device: wp.Device):
        self.device = device
        self._host = wp.empty(64, dtype=wp.int32, device="cpu", pinned=device.is_cuda)

    def read(self, arr: wp.array, index: int) -> int:
        wp.copy(self._host, arr, dest_offset=0, src_offset=index, count=1)
        if self.device.is_cuda:
            wp.synchronize_stream(wp.get_stream(self.device))
        return int(self._host.numpy()[0])

    def read_sum(self, a: wp.array, b: wp.array, index: int) -> int:
        """a[index] + b[index]: the total of an exclusive scan b of counts a."""
        wp.copy(self._host, a, dest_offset=0, src_offset=index, count=1)
        wp.copy(self._host, b, dest_offset=1, src_offset=index, count=1)
        if self.device.is_cuda:
            wp.synchronize_stream(wp.get_stream(self.device))
        values = self._host.numpy()
        return int(values[0]) + int(values[1])

    def read_array(self, arr: wp.array, count: int) -> np.ndarray:
        wp.copy(self._host, arr, count=count)
        if self.device.is_cuda:
            wp.synchronize_stream(wp.get_stream(self.device))
        return self._host.numpy()[:count].copy()


@wp.func
def locate(tree: OctreeView, cell: wp.vec3i):
    """The leaf holding finest cell `cell`: (parent node, octant in the parent, leaf level).

    The leaf is either a surface cell at the finest level or an empty child of a refined node; in both
    cases its 8 corners are among the parent's 27 lattice points.
    """
    node = int(0)
    for level in range(tree.depth):
        shift = tree.depth - level - 1
        octant = (((cell[0] >> shift) & 1) << 2) | (((cell[1] >> shift) & 1) << 1) | ((cell[2] >> shift) & 1)
        mask = tree.child_mask[node]
        bit = 1 << octant
        if (mask & bit) == 0 or level + 1 == tree.depth:
            return node, octant, level + 1
        node = tree.first_child[node] + popcount(mask & (bit - 1))
    return node, 0, tree.depth


@wp.func
def leaf_corner(tree: OctreeView, node: int, octant: int, corner: int) -> int:
    """Unique-corner index of corner `corner` (bits x, y, z) of child `octant` of internal node `node`."""
    x = ((octant >> 2) & 1) + ((corner >> 2) & 1)
    y = ((octant >> 1) & 1) + ((corner >> 1) & 1)
    z = (octant & 1) + (corner & 1)
    return tree.corner_slot[node * 27 + x * 9 + y * 3 + z]


@wp.kernel(enable_backward=False)
def _surface_cells(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    origin: wp.vec3,
    cell: float,
    resolution: int,
    shift: int,
    fill: int,
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.int64),
):
    f = wp.tid()
    tri = faces[f]
    a = vertices[tri[0]]
    b = vertices[tri[1]]
    c = vertices[tri[2]]
    pad = wp.vec3(_SLACK * cell)
    inv_cell = 1.0 / cell
    lo = quantize(wp.min(wp.min(a, b), c) - pad, origin, inv_cell, resolution)
    hi = quantize(wp.max(wp.max(a, b), c) + pad, origin, inv_cell, resolution)
    half = 0.5 * cell + _SLACK * cell
    base = int(0)
    limit = int(0)
    if fill != 0:
        base = offsets[f]
        limit = counts[f]
    found = int(0)
    for x in range(lo[0], hi[0] + 1):
        for y in range(lo[1], hi[1] + 1):
            for z in range(lo[2], hi[2] + 1):
                centre = origin + wp.vec3(float(x) + 0.5, float(y) + 0.5, float(z) + 0.5) * cell
                if triangle_overlaps_cube(a, b, c, centre, half):
                    if fill != 0 and found < limit:
                        keys[base + found] = morton3(x, y, z) << wp.int64(shift)
                    found += 1
    if fill == 0:
        counts[f] = found


@wp.kernel(enable_backward=False)
def _grow_cells(
    cells: wp.array(dtype=wp.int64),
    halo: int,
    resolution: int,
    shift: int,
    keys: wp.array(dtype=wp.int64),
):
    # cell i // width^3 and its neighbour i % width^3 within `halo` cells (clamped into the grid)
    i = wp.tid()
    width = 2 * halo + 1
    volume = width * width * width
    cell = morton3_decode(cells[i // volume] >> wp.int64(shift))
    r = i % volume
    top = resolution - 1
    x = wp.clamp(cell[0] + r // (width * width) - halo, 0, top)
    y = wp.clamp(cell[1] + (r // width) % width - halo, 0, top)
    z = wp.clamp(cell[2] + r % width - halo, 0, top)
    keys[i] = morton3(x, y, z) << wp.int64(shift)


@wp.kernel(enable_backward=False)
def _centroid_cells(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    origin: wp.vec3,
    cell: float,
    resolution: int,
    shift: int,
    keys: wp.array(dtype=wp.int64),
):
    f = wp.tid()
    tri = faces[f]
    centroid = (vertices[tri[0]] + vertices[tri[1]] + vertices[tri[2]]) / 3.0
    g = quantize(centroid, origin, 1.0 / cell, resolution)
    keys[f] = morton3(g[0], g[1], g[2]) << wp.int64(shift)


@wp.kernel(enable_backward=False)
def _mark_first_of_run(keys: wp.array(dtype=wp.int64), flags: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if i == 0 or keys[i] != keys[i - 1]:
        flags[i] = 1
    else:
        flags[i] = 0


@wp.kernel(enable_backward=False)
def _compact_runs(
    keys: wp.array(dtype=wp.int64),
    flags: wp.array(dtype=wp.int32),
    scan: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.int64),
):
    i = wp.tid()
    if flags[i] != 0:
        out[scan[i] - 1] = keys[i]


@wp.func
def _tree_node_level(prefix: wp.array(dtype=wp.int32), node: int, internal_count: int, depth: int) -> int:
    if node < 0:
        return -1
    if node < internal_count:
        return wp.min(prefix[node], 3 * depth) // 3
    return depth


@wp.kernel(enable_backward=False)
def _count_octree_nodes(
    parent: wp.array(dtype=wp.int32),
    prefix: wp.array(dtype=wp.int32),
    internal_count: int,
    depth: int,
    counts: wp.array(dtype=wp.int32),
    level_counts: wp.array(dtype=wp.int32),
):
    # Algorithm 1: the edge (parent -> node) yields the octree nodes of the levels its prefix crosses.
    node = wp.tid()
    level = _tree_node_level(prefix, node, internal_count, depth)
    parent_level = _tree_node_level(prefix, parent[node], internal_count, depth)
    counts[node] = wp.max(level - parent_level, 0)
    for lvl in range(parent_level + 1, level + 1):
        wp.atomic_add(level_counts, lvl, 1)


@wp.kernel(enable_backward=False)
def _fill_octree_nodes(
    cell_keys: wp.array(dtype=wp.int64),
    parent: wp.array(dtype=wp.int32),
    prefix: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    internal_count: int,
    depth: int,
    offsets: wp.array(dtype=wp.int32),
    node_keys: wp.array(dtype=wp.int64),
):
    node = wp.tid()
    level = _tree_node_level(prefix, node, internal_count, depth)
    parent_level = _tree_node_level(prefix, parent[node], internal_count, depth)
    leaf = node - internal_count
    if node < internal_count:
        leaf = first[node]
    key = cell_keys[leaf]
    base = offsets[node]
    for lvl in range(parent_level + 1, level + 1):
        code = key >> wp.int64(KEY_TOP_BIT - 3 * lvl)
        node_keys[base + lvl - parent_level - 1] = (wp.int64(lvl) << wp.int64(_LEVEL_SHIFT)) | code


@wp.kernel(enable_backward=False)
def _mark_first_children(node_keys: wp.array(dtype=wp.int64), flags: wp.array(dtype=wp.int32)):
    j = wp.tid()
    flags[j] = 0
    if j > 0:
        key = node_keys[j]
        previous = node_keys[j - 1]
        same_level = (key >> wp.int64(_LEVEL_SHIFT)) == (previous >> wp.int64(_LEVEL_SHIFT))
        same_parent = ((key & _CODE_MASK) >> wp.int64(3)) == ((previous & _CODE_MASK) >> wp.int64(3))
        if not (same_level and same_parent):
            flags[j] = 1


@wp.kernel(enable_backward=False)
def _link_children(
    node_keys: wp.array(dtype=wp.int64),
    flags: wp.array(dtype=wp.int32),
    scan: wp.array(dtype=wp.int32),
    child_mask: wp.array(dtype=wp.int32),
    first_child: wp.array(dtype=wp.int32),
):
    # Every node above the finest level has a first child, and levels are laid out in order, so the
    # running count of first children up to node j, less one, is the index of j's parent.
    j = wp.tid() + 1
    parent = scan[j] - 1
    octant = int(node_keys[j] & wp.int64(7))
    wp.atomic_or(child_mask, parent, 1 << octant)
    if flags[j] != 0:
        first_child[parent] = j


@wp.kernel(enable_backward=False)
def _corner_candidates(
    node_keys: wp.array(dtype=wp.int64),
    depth: int,
    keys: wp.array(dtype=wp.int64),
    slots: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    node = i // 27
    t = i - node * 27
    key = node_keys[node]
    level = int(key >> wp.int64(_LEVEL_SHIFT))
    cell = morton3_decode(key & _CODE_MASK)
    scale = depth - level
    half = 1 << (scale - 1)
    x = (cell[0] << scale) + (t // 9) * half
    y = (cell[1] << scale) + ((t // 3) % 3) * half
    z = (cell[2] << scale) + (t % 3) * half
    keys[i] = morton3(x, y, z)
    slots[i] = i


@wp.kernel(enable_backward=False)
def _number_corners(
    keys: wp.array(dtype=wp.int64),
    slots: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
    scan: wp.array(dtype=wp.int32),
    corner_slot: wp.array(dtype=wp.int32),
    corner_keys: wp.array(dtype=wp.int64),
):
    i = wp.tid()
    index = scan[i] - 1
    corner_slot[slots[i]] = index
    if flags[i] != 0:
        corner_keys[index] = keys[i]
