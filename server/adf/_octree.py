"""The octree: surface cells, their radix tree, the paper's Algorithm 1, and the de-duplicated corners.

Stages (a measuring build reads one count back after each; a planned one reads nothing, see Octree):
1. Surface cells at the finest level: every cell a triangle overlaps ("surface", the default), or the cell
   holding its centroid ("centroid", the paper's rule), grown by `halo` cells in every direction (default 1:
   then any point within one finest cell of the surface is interpolated in a finest cell, whose corners
   are exact, rather than in a large empty cell across a coarse cell boundary). One hash set keeps each
   cell once: a pass over the triangles lists the surface cells, and a pass over those adds their
   neighbours to the same set. The distinct cells are sorted by Morton code.
2. Karras's radix tree over those cell keys; the paper's Algorithm 1 turns each tree edge whose common
   prefix crosses a multiple of 3 bits into the octree nodes between the two ends, so every node is made
   exactly once and in parallel. The nodes are sorted by (level, Morton code).
3. Links: each internal node gets an 8-bit child mask and the index of its first child; children of one
   node are contiguous. A point is located by walking the masks from the root.
4. Corners: each internal node names the 27 lattice points of its 2x2x2 children; a hash set keeps each
   point once (the paper's de-duplication by corner Morton code), the distinct points are sorted by
   Morton code, and every node keeps the index of each of its 27 points in that order.
Every node above the finest level holds surface, so every internal node is refined into 8 children;
children that hold no surface are empty leaves, whose corners come from their parent's 27 points.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import warp as wp

from badf.server.adf._buffers import DeviceBuffers, HostReadback, KeptViews, SharedScratch
from badf.server.adf._bvh import link_radix_tree
from badf.server.adf._hashset import (UNLISTED, HashSet, HashSetView, NarrowHashSetView, listed_count, set_insert,
                                      with_headroom)
from badf.server.adf._geometry import KEY_TOP_BIT, morton3, morton3_decode, popcount, quantize, triangle_overlaps_cube
from badf.server.adf._tolerances import CELL_OVERLAP_SLACK

Refinement = Literal["surface", "centroid"]

LEVEL_SHIFT = 32  # octree node keys: level << 32 | Morton code of the node at its level
_LEVEL_SHIFT = wp.constant(LEVEL_SHIFT)
_CODE_MASK = wp.constant(wp.int64(0xFFFFFFFF))
# up to this depth a node key's level and code fit 31 bits as level << _NARROW_LEVEL_SHIFT | code, for the node sort
_NARROW_NODE_DEPTH = 9
_NARROW_LEVEL_SHIFT = wp.constant(27)
_NARROW_UNLISTED = wp.constant(wp.int32((1 << 31) - 1))  # level 15: after every node
_UNLISTED_KEY = wp.constant(wp.int64(UNLISTED))
_SLACK = wp.constant(CELL_OVERLAP_SLACK)
# The most threads the halo pass launches. A first measuring pass sizes it by an estimate, which for a huge
# mesh at depth 10 can pass what one launch should hold; its threads stride over the pairs beyond them.
_HALO_THREADS = 1 << 24
# A triangle whose normal's largest component is below this times its longest edge squared is a sliver:
# its plane's direction is too uncertain in float32 to bound its cells column by column.
_PLANE_MIN = wp.constant(1.0e-3)
# A triangle whose bounding box is at most this many columns of cells across is inserted by one thread;
# the rows of larger ones are shared out among the insert's threads.
_SMALL_COLUMNS = wp.constant(16)
# Threads beyond the triangles' own for those shared rows, on a GPU (the CPU runs threads in turn anyway).
_ROW_THREADS = 1 << 15
# The most rows shared out in all, as their running sums are int32: each triangle shares at most this over
# the triangle count, and its own thread takes the rest (only a mesh of millions of triangles each more than
# _SMALL_COLUMNS columns across comes near; its sums would otherwise wrap and its rows go unrefined).
_ROW_SUM_LIMIT = (1 << 31) - 1
# The first try of a measured pass over the surface cells is held to the larger of these (above).
_FIRST_TRY_CELLS = 1 << 20
_FIRST_TRY_PER_FACE = 64
# An octree over a surface smooth at the finest cells' scale, by halo: its finest cells (surface and halo) per
# cell of `sheet` (2 A / h^2, an estimate from the area A), and its internal nodes and distinct corners per
# finest cell. The largest of each over the ten meshes of ../shared/data and tests/data and a sphere, at
# depths 5, 7 and 8 (CPU, 2026-11-28); the cells per sheet cell are 3/4 of the halo's 2 halo + 1 layers.
# `Octree.plan_first_frame` plans the first frame from them; a mesh they undercount (features thinner than a
# cell, such as a wire, cross more cells than their area says) outgrows the plan, and its first frame is
# measured as before.
_SHEET_OCTREE = {0: (0.75, 0.34, 3.37), 1: (2.25, 0.22, 2.11), 2: (3.76, 0.19, 1.47)}
# The most corners a first frame is planned for. Past it the frame is measured: an estimate from the area may be
# far too large (a surface lying on copies of itself counts each again), and what it would allocate must not
# outgrow the device where the field itself fits; and a field that large spends longer in its kernels than in
# the read-backs a measured frame waits on.
_FIRST_PLAN_CORNERS = 1 << 22
_EVERYWHERE = 3.0e38  # the region box of an object without a region of interest


@wp.struct
class OctreeView:
    """What point location and interpolation read of an octree."""

    depth: int
    origin: wp.vec3  # domain corner (local coordinates)
    cell: float  # finest cell size
    region_lower: wp.vec3  # the region of interest (local coordinates): ADF queries outside it are exact
    region_upper: wp.vec3
    # 1 when every cell the surface touches is a finest leaf (refine="surface"), so no coarser leaf holds surface;
    # 0 under the paper's rule (refine="centroid"), where a large triangle crosses coarse leaves too
    coarse_leaves_clear: int
    child_mask: wp.array(dtype=wp.int32)  # (internal,) bit o set when child o holds surface
    first_child: wp.array(dtype=wp.int32)  # (internal,) node index of the first child present
    corner_slot: wp.array(dtype=wp.int32)  # (internal * 27,) unique-corner index of each lattice point


class Octree:
    """Owns one object's octree buffers; `build` remakes the tree for the current vertices.

    Its sizes vary from frame to frame. A measuring build reads each back as it goes (four read-backs)
    and sizes the buffers for it with headroom; a planned build reads nothing and runs every kernel over
    the planned capacities, each clipping the counts it reads on the device, so a frame can be captured
    as a CUDA graph. Its counts come back in the frame's report (`report`, then `take_counts`).
    """

    def __init__(self, depth: int, refine: Refinement, halo: int, buffers: DeviceBuffers):
        self.depth = depth
        self.refine = refine
        self.halo = halo
        self._views = KeptViews(OctreeView)
        self.buffers = buffers
        self.device = buffers.device
        self.host = HostReadback(self.device)
        # Arrays that live within one stage (hash tables, the radix tree, scans) share one allocation, and
        # the corner set's listed keys reuse the cells': the cells are dead by the corner stage.
        self.scratch = SharedScratch("oct.scratch", buffers)
        self.cell_set = HashSet("oct.set", buffers, self.scratch, self.host, label="cells")
        self.surface_count = buffers.ensure("oct.surface_count", 1, wp.int32)  # cells listed before the halo's
        self.surface_planned = 0  # the halo pass's threads: surface cells planned for (set by a measuring build)
        # corner keys take 3 (depth + 1) bits: up to depth 9 the corners' table holds them in 32 bits
        self.corner_set = HashSet("oct.set", buffers, self.scratch, self.host, label="corners",
                                  narrow=3 * (depth + 1) < 31)
        self._narrow_nodes = depth <= _NARROW_NODE_DEPTH  # the node keys sort in 32 bits
        self.surface_area = 0.0  # set by the owner: sizes the first frame's surface-cell set
        # planned capacities (set by a measuring build)
        self.node_capacity = 0
        self.internal_capacity = 0
        # counts of the last build, from its report (`take_counts`); a measuring build sets the ones it
        # needs on the way
        self.surface_cell_count = 0  # unique finest cells holding surface (and halo)
        self.surface_only_count = 0  # of those, the ones the surface crosses (the rest are the halo's)
        self.node_count = 0
        self.internal_count = 0
        self.level_counts = np.zeros(depth + 1, dtype=np.int64)
        self.corner_count = 0
        # device results, filled by build()
        self.cell_count: wp.array | None = None  # (1,) distinct cells (raw: may exceed the list's capacity)
        self.totals = buffers.ensure("oct.totals", 2, wp.int32)  # octree nodes, internal nodes
        self.level_starts = buffers.ensure("oct.level_starts", depth + 1, wp.int32)  # first node of each level
        self.corner_keys: wp.array | None = None
        self.corner_slot: wp.array | None = None
        self.child_mask: wp.array | None = None
        self.first_child: wp.array | None = None
        self.node_keys: wp.array | None = None
        # the finest cells that may be refined (inclusive, per axis), and the box queries interpolate in
        # (local coordinates): all of the grid and everywhere, unless a region of interest says otherwise
        top = (1 << depth) - 1
        self.region_cells = (wp.vec3i(0, 0, 0), wp.vec3i(top, top, top))
        self.region_box = (wp.vec3(-_EVERYWHERE), wp.vec3(_EVERYWHERE))
        self.has_region = False

    def plan_first_frame(self, face_count: int, side: float) -> bool:
        """Plan a first frame from the surface area (`_SHEET_OCTREE`), so that it reads nothing back until
        its end, as a later frame (a measured frame waits on the device four times); whether it did. Only
        under refine="surface": the centroid rule keeps a cell per triangle at most, which the area says
        nothing about. The frame's report tells whether the plan held (the owner measures the frame again
        if not) and, with `replan_from_counts`, sizes later frames by what it found."""
        if self.refine != "surface":
            return False
        sheet, expected = self._first_estimate(face_count, side)
        per_sheet, internal_per_cell, corners_per_cell = _SHEET_OCTREE[self.halo]
        cells = per_sheet * sheet
        # where the first try's caps bind, the area says more than the faces can be trusted to cross (a surface
        # lying on copies of itself counts each again): measured, as before (an outside check found spot at
        # depth 9, halo 2, outgrowing such a plan, and 30 squares on one another planned 30 times too large)
        if cells > expected or corners_per_cell * cells > _FIRST_PLAN_CORNERS:
            return False
        self.cell_set.planned = with_headroom(int(cells))
        self.surface_planned = with_headroom(int(0.75 * sheet))
        self.internal_capacity = with_headroom(int(internal_per_cell * cells))
        self.node_capacity = self.cell_set.planned + self.internal_capacity
        self.corner_count = int(corners_per_cell * cells)
        self.corner_set.planned = with_headroom(self.corner_count)
        return True

    def counts(self) -> tuple[int, int, int, int, int]:
        """The last frame's counts that plan later ones: cells (with the halo's), the surface's own cells, octree
        nodes, internal nodes, corners."""
        return (self.surface_cell_count, self.surface_only_count, self.node_count, self.internal_count,
                self.corner_count)

    def plan_excess(self, counts: tuple[int, int, int, int, int]) -> float:
        """How many times over the plan holds what frames of these counts (`counts`) would be planned with: the
        most of its cells, nodes and corners."""
        cells, _, nodes, _, corners = counts
        return max(self.cell_set.planned / with_headroom(cells), self.node_capacity / with_headroom(nodes),
                   self.corner_set.planned / with_headroom(corners))

    def replan_from_counts(self, counts: tuple[int, int, int, int, int] | None = None) -> float:
        """Plan later frames for the counts the last frame reported (`take_counts`), or for `counts` (as `counts()`
        orders them), as a measuring build plans them for the counts it reads; returns how many times over the old
        plan held the new one's cells or corners, whichever more."""
        cells, surface_only, nodes, internal, corners = self.counts() if counts is None else counts
        over = max(self.cell_set.planned / with_headroom(cells), self.corner_set.planned / with_headroom(corners))
        self.cell_set.planned = with_headroom(cells)
        if self.halo > 0:  # the halo pass's threads (it alone counts the cells before its own)
            self.surface_planned = with_headroom(surface_only)
        self.node_capacity = with_headroom(nodes)
        self.internal_capacity = with_headroom(internal)
        self.corner_set.planned = with_headroom(corners)
        return over

    def set_region(self, box: np.ndarray, origin: wp.vec3, side: float) -> None:
        """Refine only where `box` ((2, 3), local coordinates) needs it: finest cells the surface crosses
        within `halo` cells of the box, and their halo. So every point in the box within `halo` cells of the
        surface lies in a finest cell, as without a region. A box that misses the grid keeps the cells
        nearest it, on the grid's boundary, which hold no surface."""
        top = (1 << self.depth) - 1
        self.has_region = True
        cell = side / float(1 << self.depth)
        lattice = (box - np.array([origin[0], origin[1], origin[2]])) / cell
        lower = np.clip(np.floor(lattice[0]) - self.halo, 0, top).astype(int)
        upper = np.clip(np.floor(lattice[1]) + self.halo, 0, top).astype(int)
        self.region_cells = (wp.vec3i(*lower.tolist()), wp.vec3i(*upper.tolist()))
        # rounded inward past float32's rounding of its own corners: a point outside the box in float64 is
        # outside it in float32 too, and answered exactly (one just outside a face was interpolated before,
        # as its float32 coordinate rounded onto the face; thirteenth outside check)
        lower = np.nextafter(box[0].astype(np.float32), np.float32(np.inf))
        upper = np.nextafter(box[1].astype(np.float32), np.float32(-np.inf))
        self.region_box = (wp.vec3(*lower.tolist()), wp.vec3(*upper.tolist()))

    def build(self, vertices: wp.array, faces: wp.array, face_count: int, origin: wp.vec3, side: float, clock,
              *, measure: bool, reserve: tuple = ()) -> None:
        """The octree of one frame; a planned frame first reserves the scratch for its stages and for the
        layouts in `reserve` (what its owner lays over the scratch after it)."""
        if not measure:
            self._reserve_scratch(face_count, *reserve)
        with clock.stage("surface_cells"):
            cell_keys = self._surface_cells(vertices, faces, face_count, origin, side, measure)
        with clock.stage("octree"):
            self._octree_nodes(cell_keys, measure)
            self._link_children()
        with clock.stage("corners"):
            self._corners(measure)

    def _reserve_scratch(self, face_count: int, *after: tuple[tuple[int, type], ...]) -> None:
        """A planned frame knows every stage's sizes: its scratch takes the largest stage's room up front, with the
        layouts `after` its owner takes from it later in the frame. A first frame then grows it once, where it grew
        at the radix tree's stage and again at the corner set's, each time waiting for the device."""
        cells = self.cell_set.scratch_layout(self.cell_set.planned, self._row_layout(face_count))
        self.scratch.reserve(cells, self._tree_layout(HashSet.list_capacity_for(self.cell_set.planned)),
                             self._node_sort_layout(), self._link_layout(),
                             self.corner_set.scratch_layout(self.corner_set.planned), *after)

    def _row_layout(self, face_count: int) -> tuple[tuple[int, type], ...]:
        """Each triangle's row count and their running sum, which the surface cells' insert reads (beside the cell
        set's table in the scratch; none under the centroid rule)."""
        return ((face_count, wp.int32), (face_count, wp.int32)) if self.refine == "surface" else ()

    def planned_corner_capacity(self) -> int:
        """The corner list's capacity in a planned frame (`corner_capacity` once the frame has listed them)."""
        return HashSet.list_capacity_for(self.corner_set.planned)

    @property
    def corner_capacity(self) -> int:
        return self.corner_set.list_capacity

    def report(self) -> list[tuple[wp.array, int, int]]:
        """(device count, index, capacity) of each size a planned build must fit, for the frame's report."""
        return [(self.cell_set.view.count, 0, self.cell_set.list_capacity),
                (self.totals, 0, self.node_capacity), (self.totals, 1, self.internal_capacity),
                (self.corner_set.view.count, 0, self.corner_set.list_capacity)]

    def take_counts(self, counts: list[int], level_starts: np.ndarray, surface_only: int) -> None:
        """Record the counts a build found (in the order of `report`), its levels' first nodes, and how many
        of its finest cells the surface crosses (before the halo's)."""
        self.surface_cell_count = counts[0]
        self.surface_only_count = surface_only
        self.node_count, self.internal_count, self.corner_count = counts[-3], counts[-2], counts[-1]
        self.level_counts = np.diff(np.append(level_starts.astype(np.int64), self.node_count))

    def view(self, origin: wp.vec3, side: float) -> OctreeView:
        return self._views.view(dict(
            depth=self.depth, origin=origin, cell=side / float(1 << self.depth), region_lower=self.region_box[0],
            region_upper=self.region_box[1], coarse_leaves_clear=1 if self.refine == "surface" else 0,
            child_mask=self.child_mask, first_child=self.first_child, corner_slot=self.corner_slot))

    # -- stage 1: surface cells -------------------------------------------------------------------------
    def _surface_cells(self, vertices, faces, face_count: int, origin: wp.vec3, side: float, measure: bool) -> wp.array:
        d, halo = self.depth, self.halo
        resolution = 1 << d
        cell = side / resolution
        shift = KEY_TOP_BIT - 3 * d
        volume = (2 * halo + 1) ** 3
        kernel = _insert_surface_cells if self.refine == "surface" else _insert_centroid_cells
        expected = self._first_estimate(face_count, side)[1]

        lower, upper = self.region_cells

        def insert(table: HashSetView, *rows_and_ends: wp.array) -> None:
            if self.refine == "surface":
                # each triangle's rows of columns of cells, counted and summed, so the insert's threads share them
                rows, row_ends = rows_and_ends
                wp.launch(_count_surface_rows, dim=face_count, inputs=[vertices, faces, origin, cell, resolution, lower,
                                                                        upper, _ROW_SUM_LIMIT // face_count],
                          outputs=[rows], device=self.device)
                wp.utils.array_scan(rows, row_ends, inclusive=True)
                threads = face_count + (_ROW_THREADS if self.device.is_cuda else 0)
                wp.launch(kernel, dim=threads, inputs=[vertices, faces, face_count, rows, row_ends, origin, cell,
                                                       resolution, shift, lower, upper, threads, table],
                          device=self.device)
            else:
                wp.launch(kernel, dim=face_count, inputs=[vertices, faces, origin, cell, resolution, shift, lower, upper,
                                                          table], device=self.device)
            if self.has_region:  # one the surface stays out of would leave no cell: keep one, at its corner
                wp.launch(_insert_if_none, dim=1, inputs=[table, lower, shift], device=self.device)
            if halo > 0:
                # the surface cells are listed first; the halo pass reads them while it lists more after them.
                # Its threads cover the planned surface cells (at most _HALO_THREADS), and stride over any beyond.
                wp.copy(self.surface_count, table.count)
                threads = min(max(table.list_capacity if measure else self.surface_planned, 1) * volume, _HALO_THREADS)
                wp.launch(_insert_halo_cells, dim=threads, inputs=[table, self.surface_count, halo, resolution, shift,
                                                                   threads], device=self.device)

        self.cell_set.insert_all(expected, insert, measure=measure, beside=self._row_layout(face_count))
        if measure and halo > 0:
            self.surface_planned = with_headroom(self.host.read(self.surface_count, 0))
        keys, _ = self.cell_set.sort_listed(shift, KEY_TOP_BIT)
        self.cell_count = self.cell_set.view.count
        return keys

    def _first_estimate(self, face_count: int, side: float) -> tuple[int, int]:
        """(sheet, expected): the cells of size h that a surface of area A crosses, about 1.5 A / h^2, with
        room (2 A / h^2); and the first try of a measuring pass over the surface cells, that sheet thickened
        by the halo (2 halo + 1 cells) and held within the grid and the caps below."""
        resolution = 1 << self.depth
        cell = side / resolution
        thickness = 2 * self.halo + 1
        sheet = int(2.0 * self.surface_area / (cell * cell)) + 64
        # the centroid rule keeps no more of the sheet's cells, and at most one per triangle
        expected = thickness * (sheet if self.refine == "surface" else min(sheet, face_count))
        # the first try's table is kept for later frames: an estimate past the grid's cells would only waste it.
        # The area counts twice a surface lying on another (100 copies of a square took 945 MB of scratch at
        # depth 8 for one square's 24 MB; fifteenth outside check), so the first try is held to
        # _FIRST_TRY_CELLS or _FIRST_TRY_PER_FACE a face, whichever is more, and a measured pass grows from it
        held = max(_FIRST_TRY_CELLS, _FIRST_TRY_PER_FACE * face_count * thickness)
        return sheet, min(expected, resolution**3, held)

    # -- stage 2: Algorithm 1 over the radix tree of the cells ---------------------------------------------
    def _octree_nodes(self, cell_keys: wp.array, measure: bool) -> None:
        b, d = self.buffers, self.depth
        capacity = self.cell_set.list_capacity
        tree_nodes = 2 * capacity - 1
        # the cell set's table and slots are dead: the radix tree and its edges' counts take their place
        parent, first, prefix, ends = self.scratch.take(*self._tree_layout(capacity))
        link_radix_tree(cell_keys, self.cell_count, capacity, parent, first, prefix)

        # each edge's count of nodes, summed in place (inclusive: an edge's nodes end where its sum does; CUB's and
        # the CPU's scans both allow the input as the output), which saves an array of the tree's size
        wp.launch(_count_octree_nodes, dim=tree_nodes, inputs=[parent, prefix, self.cell_count, capacity, d],
                  outputs=[ends], device=self.device)
        wp.utils.array_scan(ends[:tree_nodes], ends[:tree_nodes], inclusive=True)
        wp.launch(_octree_totals, dim=1, inputs=[ends, self.cell_count, capacity], outputs=[self.totals],
                  device=self.device)
        if measure:
            self.node_count, self.internal_count = (int(x) for x in self.host.read_array(self.totals, 2))
            self.node_capacity = with_headroom(self.node_count)
            self.internal_capacity = with_headroom(self.internal_count)
        node_keys = b.ensure("oct.node_keys", self.node_capacity, wp.int64)
        node_keys.fill_(UNLISTED)
        wp.launch(_fill_octree_nodes, dim=tree_nodes,
                  inputs=[cell_keys, parent, prefix, first, self.cell_count, capacity, d, ends, self.node_capacity],
                  outputs=[node_keys], device=self.device)
        # The radix tree is dead by now: the sort runs in the scratch, with the room for twice the count that
        # radix_sort_pairs needs, and the sorted keys are copied back (the node keys outlive the frame; their
        # room would be 1.4 MB for the bunny). The sort's values are not used. Up to depth 9 a node's level and
        # code fit 31 bits (level << 27 | code), and the sort runs in 32 bits (2.8 MB of scratch for the bunny,
        # against 4.2).
        room, values = self.scratch.take(*self._node_sort_layout())
        if self._narrow_nodes:
            wp.launch(_narrow_node_keys, dim=self.node_capacity, inputs=[node_keys], outputs=[room], device=self.device)
            wp.utils.radix_sort_pairs(room, values, self.node_capacity, end_bit=31)
            wp.launch(_widen_node_keys, dim=self.node_capacity, inputs=[room], outputs=[node_keys], device=self.device)
        else:
            wp.copy(room, node_keys, count=self.node_capacity)
            wp.utils.radix_sort_pairs(room, values, self.node_capacity, end_bit=LEVEL_SHIFT + 4)
            wp.copy(node_keys, room, count=self.node_capacity)
        self.node_keys = node_keys

    @staticmethod
    def _tree_layout(capacity: int) -> tuple[tuple[int, type], ...]:
        """The radix tree over `capacity` cells (parent, first, prefix: Algorithm 1 reads no children) and the running
        sum of its edges' node counts, in the scratch."""
        tree_nodes = 2 * capacity - 1
        return (tree_nodes, wp.int32), (capacity, wp.int32), (capacity, wp.int32), (tree_nodes, wp.int32)

    def _node_sort_layout(self) -> tuple[tuple[int, type], ...]:
        keys = wp.int32 if self._narrow_nodes else wp.int64
        return (2 * self.node_capacity, keys), (2 * self.node_capacity, wp.int32)

    # -- stage 3: child masks and first children ----------------------------------------------------------
    def _link_layout(self) -> tuple[tuple[int, type], ...]:
        """The first-child flags and their scan, over the planned nodes."""
        return (self.node_capacity, wp.int32), (self.node_capacity, wp.int32)

    def _link_children(self) -> None:
        b = self.buffers
        nodes, internal = self.node_capacity, self.internal_capacity
        flags, scan = self.scratch.take(*self._link_layout())
        self.child_mask = b.ensure("oct.child_mask", internal, wp.int32)
        self.first_child = b.ensure("oct.first_child", internal, wp.int32)
        self.child_mask.zero_()
        wp.launch(_mark_first_children, dim=nodes, inputs=[self.node_keys, self.totals],
                  outputs=[flags, self.level_starts], device=self.device)
        wp.utils.array_scan(flags[:nodes], scan[:nodes], inclusive=True)
        wp.launch(_link_children, dim=nodes, inputs=[self.node_keys, self.totals, flags, scan, internal],
                  outputs=[self.child_mask, self.first_child], device=self.device)

    # -- stage 4: corners ---------------------------------------------------------------------------------
    def _corners(self, measure: bool) -> None:
        b, d = self.buffers, self.depth
        candidates = 27 * self.internal_capacity
        self.corner_slot = b.ensure("oct.corner_slot", candidates, wp.int32)
        count = self.corner_set.insert_all(
            10 * self.internal_count,
            lambda table: wp.launch(_insert_corners, dim=candidates, inputs=[self.node_keys, self.totals, d, table],
                                    outputs=[self.corner_slot], device=self.device),
            measure=measure,
        )
        keys, slots = self.corner_set.sort_listed(0, 3 * (d + 1))
        table = self.corner_set.view
        rank = self.corner_set.spent_table()
        wp.launch(_rank_slots, dim=table.list_capacity, inputs=[slots, table], outputs=[rank], device=self.device)
        wp.launch(_slots_to_ranks, dim=candidates, inputs=[rank, self.totals], outputs=[self.corner_slot],
                  device=self.device)
        if measure:
            self.corner_count = count  # this frame's search split is chosen from it
        self.corner_keys = keys


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
def lattice_point(octant: int, corner: int) -> int:
    """Which of an internal node's 27 lattice points (x * 9 + y * 3 + z) is corner `corner` (bits x, y, z) of
    its child `octant`."""
    x = ((octant >> 2) & 1) + ((corner >> 2) & 1)
    y = ((octant >> 1) & 1) + ((corner >> 1) & 1)
    z = (octant & 1) + (corner & 1)
    return x * 9 + y * 3 + z


@wp.func
def leaf_corner(tree: OctreeView, node: int, octant: int, corner: int) -> int:
    """Unique-corner index of corner `corner` (bits x, y, z) of child `octant` of internal node `node`."""
    return tree.corner_slot[node * 27 + lattice_point(octant, corner)]


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
    cell_count: wp.array(dtype=wp.int32),
    cell_capacity: int,
    depth: int,
    counts: wp.array(dtype=wp.int32),
):
    # Algorithm 1: the edge (parent -> node) yields the octree nodes of the levels its prefix crosses.
    node = wp.tid()
    cells = wp.min(cell_count[0], cell_capacity)
    counts[node] = 0
    if node >= 2 * cells - 1:
        return
    internal_count = cells - 1
    level = _tree_node_level(prefix, node, internal_count, depth)
    parent_level = _tree_node_level(prefix, parent[node], internal_count, depth)
    counts[node] = wp.max(level - parent_level, 0)


@wp.kernel(enable_backward=False)
def _octree_totals(ends: wp.array(dtype=wp.int32), cell_count: wp.array(dtype=wp.int32), cell_capacity: int,
                   totals: wp.array(dtype=wp.int32)):
    # all nodes: the running sum's end; the finest level's nodes are the cells themselves (each tree leaf is one)
    cells = wp.min(cell_count[0], cell_capacity)
    totals[0] = ends[2 * cells - 2]
    totals[1] = totals[0] - cells


@wp.kernel(enable_backward=False)
def _fill_octree_nodes(
    cell_keys: wp.array(dtype=wp.int64),
    parent: wp.array(dtype=wp.int32),
    prefix: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    cell_count: wp.array(dtype=wp.int32),
    cell_capacity: int,
    depth: int,
    ends: wp.array(dtype=wp.int32),
    node_capacity: int,
    node_keys: wp.array(dtype=wp.int64),
):
    node = wp.tid()
    cells = wp.min(cell_count[0], cell_capacity)
    if node >= 2 * cells - 1:
        return
    internal_count = cells - 1
    level = _tree_node_level(prefix, node, internal_count, depth)
    parent_level = _tree_node_level(prefix, parent[node], internal_count, depth)
    leaf = node - internal_count
    if node < internal_count:
        leaf = first[node]
    key = cell_keys[leaf]
    base = ends[node] - wp.max(level - parent_level, 0)  # where this edge's nodes start (_count_octree_nodes)
    for lvl in range(parent_level + 1, level + 1):
        code = key >> wp.int64(KEY_TOP_BIT - 3 * lvl)
        index = base + lvl - parent_level - 1
        if index < node_capacity:
            node_keys[index] = (wp.int64(lvl) << wp.int64(_LEVEL_SHIFT)) | code


@wp.kernel(enable_backward=False)
def _narrow_node_keys(keys: wp.array(dtype=wp.int64), narrow: wp.array(dtype=wp.int32)):
    i = wp.tid()
    key = keys[i]
    level = int(key >> wp.int64(_LEVEL_SHIFT))
    narrow[i] = wp.where(key == _UNLISTED_KEY, _NARROW_UNLISTED,
                         wp.int32((wp.int64(level) << wp.int64(_NARROW_LEVEL_SHIFT)) | (key & _CODE_MASK)))


@wp.kernel(enable_backward=False)
def _widen_node_keys(narrow: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int64)):
    i = wp.tid()
    key = narrow[i]
    level = wp.int64(key >> _NARROW_LEVEL_SHIFT)
    code = wp.int64(key & ((1 << _NARROW_LEVEL_SHIFT) - 1))
    keys[i] = wp.where(key == _NARROW_UNLISTED, _UNLISTED_KEY, (level << wp.int64(_LEVEL_SHIFT)) | code)


@wp.kernel(enable_backward=False)
def _mark_first_children(node_keys: wp.array(dtype=wp.int64), totals: wp.array(dtype=wp.int32),
                         flags: wp.array(dtype=wp.int32), level_starts: wp.array(dtype=wp.int32)):
    # flags the first child of each parent, and records where each level starts (nodes are sorted by level)
    j = wp.tid()
    flags[j] = 0
    if j == 0:
        level_starts[0] = 0
    elif j < totals[0]:
        key = node_keys[j]
        previous = node_keys[j - 1]
        level = int(key >> wp.int64(_LEVEL_SHIFT))
        same_level = level == int(previous >> wp.int64(_LEVEL_SHIFT))
        same_parent = ((key & _CODE_MASK) >> wp.int64(3)) == ((previous & _CODE_MASK) >> wp.int64(3))
        if not same_level:
            level_starts[level] = j
        if not (same_level and same_parent):
            flags[j] = 1


@wp.kernel(enable_backward=False)
def _link_children(
    node_keys: wp.array(dtype=wp.int64),
    totals: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
    scan: wp.array(dtype=wp.int32),
    internal_capacity: int,
    child_mask: wp.array(dtype=wp.int32),
    first_child: wp.array(dtype=wp.int32),
):
    # Every node above the finest level has a first child, and levels are laid out in order, so the
    # running count of first children up to node j, less one, is the index of j's parent.
    j = wp.tid()
    if j == 0 or j >= totals[0]:
        return
    parent = scan[j] - 1
    if parent >= internal_capacity:
        return  # more nodes than planned: the frame is measured again
    octant = int(node_keys[j] & wp.int64(7))
    wp.atomic_or(child_mask, parent, 1 << octant)
    if flags[j] != 0:
        first_child[parent] = j


@wp.func
def _cell_range_lower(a: wp.vec3, b: wp.vec3, c: wp.vec3, origin: wp.vec3, cell: float, resolution: int,
                      region_lower: wp.vec3i) -> wp.vec3i:
    """The lowest finest cell (per axis) the triangle's padded bounding box reaches, within the region's."""
    pad = wp.vec3(_SLACK * cell)
    return wp.max(quantize(wp.min(wp.min(a, b), c) - pad, origin, 1.0 / cell, resolution), region_lower)


@wp.func
def _cell_range_upper(a: wp.vec3, b: wp.vec3, c: wp.vec3, origin: wp.vec3, cell: float, resolution: int,
                      region_upper: wp.vec3i) -> wp.vec3i:
    pad = wp.vec3(_SLACK * cell)
    return wp.min(quantize(wp.max(wp.max(a, b), c) + pad, origin, 1.0 / cell, resolution), region_upper)


@wp.func
def _column_axis(n: wp.vec3) -> int:
    """The axis a triangle of normal n is walked along: its normal's largest component (0 for n = 0)."""
    m = wp.abs(n)
    if m[2] > m[0] and m[2] > m[1]:
        return 2
    if m[1] > m[0]:
        return 1
    return 0


@wp.func
def _lattice(axis: int, u: int, v: int, w: int) -> wp.vec3i:
    """Cell (x, y, z) from its coordinates across (u, v: the axes after `axis`, in turn) and along `axis`."""
    if axis == 0:
        return wp.vec3i(w, u, v)
    if axis == 1:
        return wp.vec3i(v, w, u)
    return wp.vec3i(u, v, w)


@wp.func
def _rows_across(a: wp.vec3, b: wp.vec3, c: wp.vec3, origin: wp.vec3, cell: float, resolution: int,
                 region_lower: wp.vec3i, region_upper: wp.vec3i) -> wp.vec2i:
    """(rows, columns per row) of the triangle's bounding box of cells seen along its normal's largest axis
    (rows along the axis after it); (0, 0) where the box misses the region's cells."""
    lo = _cell_range_lower(a, b, c, origin, cell, resolution, region_lower)
    hi = _cell_range_upper(a, b, c, origin, cell, resolution, region_upper)
    if hi[0] < lo[0] or hi[1] < lo[1] or hi[2] < lo[2]:
        return wp.vec2i(0, 0)
    w = _column_axis(wp.cross(b - a, c - a))
    u = (w + 1) % 3
    v = (w + 2) % 3
    return wp.vec2i(hi[u] - lo[u] + 1, hi[v] - lo[v] + 1)


@wp.kernel(enable_backward=False)
def _count_surface_rows(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    origin: wp.vec3,
    cell: float,
    resolution: int,
    region_lower: wp.vec3i,
    region_upper: wp.vec3i,
    most_shared: int,
    rows: wp.array(dtype=wp.int32),
):
    # the rows of a large triangle's bounding box shared out by the insert, up to most_shared (its own thread
    # takes the rest); 0 for a triangle its own thread takes whole
    f = wp.tid()
    tri = faces[f]
    span = _rows_across(vertices[tri[0]], vertices[tri[1]], vertices[tri[2]], origin, cell, resolution,
                        region_lower, region_upper)
    count = int(0)
    if span[0] * span[1] > _SMALL_COLUMNS:
        count = wp.min(span[0], most_shared)
    rows[f] = count


@wp.func
def _insert_row(a: wp.vec3, b: wp.vec3, c: wp.vec3, row: int, origin: wp.vec3, cell: float, resolution: int,
                shift: int, region_lower: wp.vec3i, region_upper: wp.vec3i, table: HashSetView):
    """Insert the finest cells the triangle overlaps (separating axes) in one row of its bounding box's
    columns: seen along its normal's largest axis w, row `row` (counted from the box's lowest) along u.
    Each column meets the triangle's plane over at most 2 cells plus its slack; a sliver, whose plane is not
    known well enough in float32, takes its bounding box's whole column."""
    lo = _cell_range_lower(a, b, c, origin, cell, resolution, region_lower)
    hi = _cell_range_upper(a, b, c, origin, cell, resolution, region_upper)
    n = wp.cross(b - a, c - a)
    w = _column_axis(n)
    u = (w + 1) % 3
    v = (w + 2) % 3
    cu = lo[u] + row
    half = 0.5 * cell + _SLACK * cell
    longest = wp.max(wp.max(wp.length_sq(b - a), wp.length_sq(c - a)), wp.length_sq(c - b))
    # a box at most 3 cells deep along w gains nothing from the plane (most triangles, smaller than a cell)
    planar = hi[w] - lo[w] > 2 and wp.abs(n[w]) >= _PLANE_MIN * longest and n[w] != 0.0
    su = float(0.0)
    sv = float(0.0)
    if planar:
        su = n[u] / n[w]
        sv = n[v] / n[w]
    inv_cell = 1.0 / cell
    top = float(resolution) + 1.0
    u0 = origin[u] + (float(cu) - _SLACK) * cell - a[u]
    u1 = origin[u] + (float(cu) + 1.0 + _SLACK) * cell - a[u]
    for cv in range(lo[v], hi[v] + 1):
        w_lo = lo[w]
        w_hi = hi[w]
        if planar:
            # the plane's extent along w over the column grown by the slack, plus a cell each way for rounding;
            # clamped in floats first, as a steep plane's far corners can pass what an int holds
            v0 = origin[v] + (float(cv) - _SLACK) * cell - a[v]
            v1 = origin[v] + (float(cv) + 1.0 + _SLACK) * cell - a[v]
            w00 = a[w] - su * u0 - sv * v0
            w10 = a[w] - su * u1 - sv * v0
            w01 = a[w] - su * u0 - sv * v1
            w11 = a[w] - su * u1 - sv * v1
            low = (wp.min(wp.min(w00, w10), wp.min(w01, w11)) - origin[w]) * inv_cell
            high = (wp.max(wp.max(w00, w10), wp.max(w01, w11)) - origin[w]) * inv_cell
            w_lo = wp.max(w_lo, int(wp.floor(wp.clamp(low, -2.0, top))) - 1)
            w_hi = wp.min(w_hi, int(wp.floor(wp.clamp(high, -2.0, top))) + 1)
        for cw in range(w_lo, w_hi + 1):
            lattice = _lattice(w, cu, cv, cw)
            centre = origin + wp.vec3(float(lattice[0]) + 0.5, float(lattice[1]) + 0.5, float(lattice[2]) + 0.5) * cell
            if triangle_overlaps_cube(a, b, c, centre, half):
                set_insert(table, morton3(lattice[0], lattice[1], lattice[2]) << wp.int64(shift))


@wp.kernel(enable_backward=False)
def _insert_surface_cells(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    face_count: int,
    rows: wp.array(dtype=wp.int32),
    row_ends: wp.array(dtype=wp.int32),
    origin: wp.vec3,
    cell: float,
    resolution: int,
    shift: int,
    region_lower: wp.vec3i,
    region_upper: wp.vec3i,
    threads: int,
    table: HashSetView,
):
    # Every finest cell a triangle overlaps. Thread f takes triangle f whole when its bounding box is at most
    # _SMALL_COLUMNS columns across (nearly every triangle of a fine mesh); the rows of the larger ones are
    # shared out (up to their cap, the rest taken by their own thread), a run of them per thread, row i
    # belonging to the first triangle whose running row count passes i. One thread per triangle over its
    # whole bounding box had a large triangle oblique to the axes test up to resolution^3 cells in turn (a
    # floor of two triangles).
    i = wp.tid()
    if i < face_count:
        tri = faces[i]
        a = vertices[tri[0]]
        b = vertices[tri[1]]
        c = vertices[tri[2]]
        span = _rows_across(a, b, c, origin, cell, resolution, region_lower, region_upper)
        for row in range(rows[i], span[0]):  # the rows not shared out: all of a small triangle's
            _insert_row(a, b, c, row, origin, cell, resolution, shift, region_lower, region_upper, table)
    total = row_ends[face_count - 1]
    # each thread takes a run of rows in turn, so the rows of one triangle go in order (the CPU runs the
    # threads one after the other: rows taken by stride scattered its inserts over the set)
    per = (total + threads - 1) // threads
    i = wp.tid() * per
    end = wp.min(i + per, total)
    while i < end:
        first = int(0)
        last = face_count - 1
        while first < last:
            middle = (first + last) // 2
            if row_ends[middle] > i:
                last = middle
            else:
                first = middle + 1
        start = int(0)
        if first > 0:
            start = row_ends[first - 1]
        tri = faces[first]
        _insert_row(vertices[tri[0]], vertices[tri[1]], vertices[tri[2]], i - start, origin, cell, resolution, shift,
                    region_lower, region_upper, table)
        i += 1


@wp.kernel(enable_backward=False)
def _insert_centroid_cells(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    origin: wp.vec3,
    cell: float,
    resolution: int,
    shift: int,
    region_lower: wp.vec3i,
    region_upper: wp.vec3i,
    table: HashSetView,
):
    f = wp.tid()
    tri = faces[f]
    centroid = (vertices[tri[0]] + vertices[tri[1]] + vertices[tri[2]]) / 3.0
    g = quantize(centroid, origin, 1.0 / cell, resolution)
    if g == wp.min(wp.max(g, region_lower), region_upper):  # within the region's cells
        set_insert(table, morton3(g[0], g[1], g[2]) << wp.int64(shift))


@wp.kernel(enable_backward=False)
def _insert_if_none(table: HashSetView, cell: wp.vec3i, shift: int):
    if table.count[0] == 0:
        set_insert(table, morton3(cell[0], cell[1], cell[2]) << wp.int64(shift))


@wp.kernel(enable_backward=False)
def _insert_halo_cells(
    cells: HashSetView,
    surface_count: wp.array(dtype=wp.int32),
    halo: int,
    resolution: int,
    shift: int,
    stride: int,
):
    # listed cell i // width^3 (one of the first surface_count, listed before this pass) and its neighbour
    # i % width^3 within `halo` cells (clamped into the grid), for i = tid, tid + stride, ...
    width = 2 * halo + 1
    volume = width * width * width
    total = wp.min(surface_count[0], cells.list_capacity) * volume
    top = resolution - 1
    i = wp.tid()
    while i < total:
        cell = morton3_decode(cells.listed_keys[i // volume] >> wp.int64(shift))
        r = i % volume
        x = wp.clamp(cell[0] + r // (width * width) - halo, 0, top)
        y = wp.clamp(cell[1] + (r // width) % width - halo, 0, top)
        z = wp.clamp(cell[2] + r % width - halo, 0, top)
        set_insert(cells, morton3(x, y, z) << wp.int64(shift))
        i += stride


@wp.kernel(enable_backward=False)
def _insert_corners(
    node_keys: wp.array(dtype=wp.int64),
    totals: wp.array(dtype=wp.int32),
    depth: int,
    table: Any,  # HashSetView or NarrowHashSetView (overloads below)
    corner_slot: wp.array(dtype=wp.int32),
):
    # lattice point t (x, y, z in 0..2) of the children of internal node i // 27; its table slot for now
    i = wp.tid()
    node = i // 27
    if node >= totals[1]:
        return
    t = i - node * 27
    key = node_keys[node]
    level = int(key >> wp.int64(_LEVEL_SHIFT))
    cell = morton3_decode(key & _CODE_MASK)
    scale = depth - level
    half = 1 << (scale - 1)
    x = (cell[0] << scale) + (t // 9) * half
    y = (cell[1] << scale) + ((t // 3) % 3) * half
    z = (cell[2] << scale) + (t % 3) * half
    corner_slot[i] = set_insert(table, morton3(x, y, z))


@wp.kernel(enable_backward=False)
def _rank_slots(slots: wp.array(dtype=wp.int32), table: Any, rank: wp.array(dtype=wp.int32)):
    r = wp.tid()
    if r < listed_count(table):
        rank[slots[r]] = r


for _view in (HashSetView, NarrowHashSetView):  # the corners' table, in 64 bits or (up to depth 9) in 32
    wp.overload(_insert_corners, {"table": _view})
    wp.overload(_rank_slots, {"table": _view})


@wp.kernel(enable_backward=False)
def _slots_to_ranks(rank: wp.array(dtype=wp.int32), totals: wp.array(dtype=wp.int32),
                    corner_slot: wp.array(dtype=wp.int32)):
    i = wp.tid()
    slot = corner_slot[i]
    if i // 27 < totals[1] and slot >= 0:  # -1: the table was full, and the frame is measured again
        corner_slot[i] = rank[slot]
