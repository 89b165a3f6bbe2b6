"""The BVH: triangles sorted by Morton code, Karras's (2012) radix tree over the codes, bottom-up refit.

Nodes live in one index space of 2n - 1: internal nodes 0..n-2 (0 is the root), then leaf k at n - 1 + k,
where leaf k is the k-th triangle in Morton order. The same radix-tree kernel builds the hierarchy the
octree is read from (paper, Algorithm 1), over the sorted surface-cell keys instead of triangle keys.

Each internal node i keeps its two children in slots 2i and 2i + 1 (their node ids), which the winding numbers
walk; triangles are packed three vec4 per leaf, and the winding-number moments four vec4 per internal node.

The searches walk a 4-wide view of the same tree (`WideTree`): every other level folded away, so a node's
children are its binary node's grandchildren (or a child itself where that is a single triangle). A visit reads
the four boxes as six 16-byte planes (the lower x of all four, then y, ..., then the upper z) and tests them
together; a walk takes about half the dependent steps of a binary one. On the H100 the bunny's corner searches
took 1.02 against 1.35 ms over the binary tree (2026-11-28, `bench/probes/probe_bvh4.py`), with the same answers.
The boxes live only there: the refit climbs the view, writing each box into its entry of the parent's planes,
and merges the moments of a view's node and of the binary nodes between it and its entries. (The binary tree's
own boxes, both children's per node, were dropped on 2026-11-28: 4.4 MB for the bunny.)

The winding numbers (Barill et al. 2018) replace a node far from the point by the first two terms of its
expansion: the dipole (the sum of area-weighted normals) and the first moment of the normals about the
node's centre, of which only the symmetric part contributes. The second term lets the expansion hold to
the same accuracy with a node radius bounded tighter than the usual sum of child radii: each child's
contribution to its parent's radius is the smaller of that sum and its box's farthest corner. On the
bunny's depth-7 corners this visits 0.63 times the nodes of the dipole alone with the summed radius, with
the same largest error (4.2e-2 against 4.4e-2 of a float64 oracle's winding number).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from badf.server.adf._buffers import DeviceBuffers, KeptViews
from badf.server.adf._bvh_shape import Shape
from badf.server.adf._geometry import (
    KEY_TOP_BIT,
    box_distance_sq,
    clz64,
    load_coherent_vec4,
    load_vec4,
    morton3,
    quantize,
    solid_angle_careful,
    solid_angle_checked,
    stack_int,
    thread_fence,
    triangle_distance_sq,
)
from badf.server.adf._tolerances import (BOX_SLACK, FAT_AREA, RELINK_SPREAD, RELINK_SPREAD_FLOOR, RERUN_SPREAD,
                                         RIM_TRUST, SOUP_AREA, WINDING_BUDGET, WINDING_FAR_FIELD,
                                         WINDING_FAR_FIELD_SAH)

_BOX_SLACK = wp.constant(BOX_SLACK)
_INV_FOUR_PI = wp.constant(1.0 / (4.0 * math.pi))
_RIM_TRUST = wp.constant(RIM_TRUST)
LEAF_SIZE = wp.constant(1)
UNLIMITED_VISITS = wp.constant(2**31 - 1)
# A 4-wide node's entry with no child; its box is EMPTY_BOX..-EMPTY_BOX, which no point comes within reach of.
NO_CHILD = wp.constant(2**31 - 1)
EMPTY_BOX = wp.constant(3.0e38)
# The binary tree is at most 62 levels deep (its keys' bits), so the 4-wide one at most 31; a walk's stack holds
# at most three waiting siblings a level and the node it is on.
WIDE_STACK_DEPTH = 3 * 31 + 1
wide_stack_int = wp.types.vector(length=WIDE_STACK_DEPTH, dtype=wp.int32)
wide_stack_float = wp.types.vector(length=WIDE_STACK_DEPTH, dtype=wp.float32)


def code_layout(face_count: int) -> tuple[int, int]:
    """(levels, index bits) of the BVH's keys for `face_count` triangles.

    A key is the Morton code of the triangle's centroid on a grid of 2^levels cells per axis, with the face
    index in the low `index bits` below it, so every key is unique and within 62 bits (the radix tree over
    it is then at most 62 levels deep, which the searches' stacks hold). The code takes every bit the index
    leaves: 15 levels for the bunny's 69,451 triangles, 13 up to 2^23 triangles and 12 up to 2^26. A fixed 10
    put a mesh's dense part in a handful of cells when a part 1,000 times smaller than the domain lay far from
    the rest; their triangles were ordered by index there, and exact queries near them took 16 times as long
    (CPU).
    """
    index_bits = max(1, (face_count - 1).bit_length())
    return min(21, (KEY_TOP_BIT - index_bits) // 3), index_bits


@wp.struct
class BvhView:
    """What the query kernels read of a BVH."""

    internal_count: int
    code_levels: int  # the keys' layout (`code_layout`), for spatial seeds
    index_bits: int
    slot_child: wp.array(dtype=wp.int32)  # (2(n-1),) node id of child s of node s // 2
    triangles: wp.array(dtype=wp.vec4)  # (3n,) corners a, b, c of each leaf (Morton order), xyz
    leaf_face: wp.array(dtype=wp.int32)  # (n,) face index of each leaf
    face_leaf: wp.array(dtype=wp.int32)  # (n,) leaf of each face
    leaf_key: wp.array(dtype=wp.int64)  # (n,) the triangles' keys, sorted, for spatial seeds
    # the leaf of each sorted key: (n,) for a tree whose leaves are not in key order (the SAH's shape), else (1,)
    # and unread, leaf k holding key k
    key_leaf: wp.array(dtype=wp.int32)
    keys_in_leaf_order: int
    # node radii beyond which a winding-number walk takes a node's expansion (WINDING_FAR_FIELD, by the tree's shape)
    far_field: float
    # internal nodes a winding-number walk opens at most (WINDING_BUDGET) in a soup (a surface of more than
    # `soup_area` times its root's sphere's area: SOUP_AREA) or on a tree that misfits the frame (`leaf_spread`),
    # counting only nodes of more than `fat_area` times their disc's area (FAT_AREA), and the counts of walks cut
    # short by it: the frame's (slot 0) and the last query's (slot 1), this view's in `cut_slot`
    winding_budget: int
    soup_area: float
    fat_area: float
    winding_cuts: wp.array(dtype=wp.int32)
    cut_slot: int
    # Bvh.measure_spread's sums: this frame's (gaps, sizes), then those of the frame the tree was linked on
    leaf_spread: wp.array(dtype=wp.int64)
    # Fast-winding-number moments of each internal node i, four vec4 (a one-element array when the sign
    # does not need them). A single triangle's are worked out from it where needed (`leaf_moments`): its
    # first moment about its centroid is zero, so storing them would only repeat the triangle.
    #   4i: area-weighted centroid; w: a radius bounding the node around it
    #   4i + 1: sum of area-weighted normals; w: total area
    #   4i + 2, 4i + 3: symmetric part S of sum(area * normal x (centroid - centre)): (Sxx, Syy, Szz, Sxy),
    #   (Sxz, Syz, 0, 0)
    node_moments: wp.array(dtype=wp.vec4)
    # The 4-wide view (`WideTree`): node k's four boxes as six planes, wide_planes[6k..6k+5] (x, y, z of the four
    # lower corners, then of the four upper ones), and its four entries, wide_child[4k..4k+3]: a 4-wide node
    # (>= 0), a single triangle's leaf (-1 - leaf), or NO_CHILD. Node 0 is the root.
    wide_planes: wp.array(dtype=wp.vec4)
    wide_child: wp.array(dtype=wp.int32)
    wide_first: wp.array(dtype=wp.int32)  # the first leaf under each 4-wide node (the queries' tie test)
    # The fans that close the mesh's rim (`_sign.rim_fans`), three corners each, this frame's; rim_count 0: none
    rim: wp.array(dtype=wp.vec3)
    rim_count: int


class Bvh:
    """Owns the BVH's device buffers for one mesh; `build` sorts and links, `refit` updates the boxes.

    Its shape is Karras's radix tree over the triangles' Morton codes, linked at each build, unless a `shape` is
    given (`_bvh_shape.sah_shape`): that tree is linked at the first build and kept, and later builds (a frame that
    moves the domain) only sort the keys that seed searches without a last frame's faces."""

    def __init__(self, face_count: int, *, with_moments: bool, buffers: DeviceBuffers, shape: Shape | None = None,
                 rim: np.ndarray | None = None):
        self.face_count = face_count
        self.shape = shape if face_count > 1 else None
        self.far_field = WINDING_FAR_FIELD if self.shape is None else WINDING_FAR_FIELD_SAH
        self.winding_budget, self.soup_area, self.fat_area = WINDING_BUDGET, SOUP_AREA, FAT_AREA
        self._shape_linked = False
        self.internal_count = face_count - 1
        self.code_levels, self.index_bits = code_layout(face_count)
        self.with_moments = with_moments
        self.device = buffers.device
        n, slots = face_count, max(2 * (face_count - 1), 1)
        b = buffers
        # the sorted keys (the spatial seeds read them) and the face of each leaf (the refit reads them)
        self.leaf_key = b.array("bvh.leaf_key", n, wp.int64)
        self.leaf_face = b.array("bvh.leaf_face", n, wp.int32)
        self.face_leaf = b.array("bvh.face_leaf", n, wp.int32)  # inverse of leaf_face
        self.key_leaf = b.array("bvh.key_leaf", n if self.shape is not None else 1, wp.int32)
        self.leaf_count = b.array("bvh.leaf_count", 1, wp.int32)
        self.leaf_count.fill_(n)
        self.slot_child = b.array("bvh.slot_child", slots, wp.int32)
        self.wide = WideTree(n, b)
        self._buffers = b
        self._allocate_geometry(empty_boxes=False)  # the view's link empties them
        # the rim's fans (vertex ids), and their corners in this frame, written by each refit
        self.rim_count = 0 if rim is None else len(rim)
        self.rim_faces = b.array("bvh.rim_faces", max(self.rim_count, 1), wp.vec3i)
        if self.rim_count:
            self.rim_faces.assign(rim)
        self.rim = b.array("bvh.rim", 3 * max(self.rim_count, 1), wp.vec3)
        self._cuts: dict[int, wp.array] = {}
        # the walks cut, the frame's (zeroed by each frame, read with its report) and the last query's
        self.winding_cuts = b.array("bvh.winding_cuts", 2, wp.int32)
        self.query_cuts = self.winding_cuts[1:2]  # zeroed by each query (a view made once)
        # measure_spread's sums, this frame's (read with its report) and the linking frame's (zero: never measured)
        self.leaf_spread = b.array("bvh.leaf_spread", 4, wp.int64)
        self._views = KeptViews(BvhView)

    def _allocate_geometry(self, *, empty_boxes: bool) -> None:
        """The arrays a refit writes in full: the triangles packed for the searches, the winding moments and the
        4-wide view's boxes (with `empty_boxes`, those of absent entries empty, as the view's link leaves them)."""
        n, b = self.face_count, self._buffers
        # all three or none: a device that cannot hold the last leaves the BVH without geometry, as it was
        triangles = b.array("bvh.triangles", 3 * n, wp.vec4)
        moments = b.array("bvh.node_moments", 4 * max(n - 1, 1) if self.with_moments else 1, wp.vec4)
        planes = b.array("bvh.wide.planes", 6 * self.wide.capacity, wp.vec4)
        if empty_boxes:
            wp.launch(_empty_planes, dim=6 * self.wide.capacity, inputs=[planes], device=self.device)
        self.triangles, self.node_moments, self.wide.planes = triangles, moments, planes

    @property
    def holds_geometry(self) -> bool:
        return self.triangles is not None

    def give_back_geometry(self) -> bool:
        """Free what a refit writes in full (the boxes, the packed triangles and the winding moments: 12.2 MB of the
        bunny's 16.7), for an object that sits idle; `hold_geometry` makes it again. Whether it was held. Nothing may
        read it until then (the owner drops any captured graph, and views taken before)."""
        held = self.holds_geometry
        if held:
            wp.synchronize_device(self.device)
        self._views.clear()  # a kept view would hold the arrays
        self.triangles = self.node_moments = self.wide.planes = None
        for name in ("bvh.triangles", "bvh.node_moments", "bvh.wide.planes"):  # also what a failed hold made
            self._buffers.release(name)
        return held

    def hold_geometry(self, vertices: wp.array, faces: wp.array) -> bool:
        """Make what `give_back_geometry` freed again, refitted to `vertices` (the frame the tree was last refitted
        to gives back the same arrays, bit for bit: a refit's merges do not depend on the order threads arrive in);
        the device is waited for, so that work on any stream may read it. Whether it had to."""
        if self.holds_geometry:
            return False
        try:
            self._allocate_geometry(empty_boxes=True)
            self.refit(vertices, faces)
            wp.synchronize_device(self.device)
        except BaseException:
            self.give_back_geometry()  # not half made: the next query or frame tries again
            raise
        return True

    def build(self, vertices: wp.array, faces: wp.array, origin: wp.vec3, side: float) -> None:
        """Sort the triangles by the Morton code of their centroid in the domain and link the tree on them (a given
        shape: link it the first time, and after only sort the keys, which seed searches)."""
        n = self.face_count
        b = self._buffers
        # what only a build uses: the sort, with its room for twice the count, and the tree's links (given back by
        # `give_back_build`)
        keys = b.ensure("bvh.build.keys", 2 * n, wp.int64)
        order = b.ensure("bvh.build.faces", 2 * n, wp.int32)
        resolution = 1 << self.code_levels
        wp.launch(
            _triangle_keys,
            dim=n,
            inputs=[vertices, faces, origin, resolution / side, resolution, self.index_bits],
            outputs=[keys, order],
            device=self.device,
        )
        wp.utils.radix_sort_pairs(keys, order, n)
        wp.copy(self.leaf_key, keys, count=n)
        if self.shape is not None:
            if not self._shape_linked:
                self._link_shape()
            wp.launch(_leaf_of_key, dim=n, inputs=[order, self.face_leaf], outputs=[self.key_leaf], device=self.device)
            return
        wp.copy(self.leaf_face, order, count=n)
        wp.launch(_invert_order, dim=n, inputs=[self.leaf_face], outputs=[self.face_leaf], device=self.device)
        if n > 1:
            left = b.ensure("bvh.build.left", n - 1, wp.int32)
            right = b.ensure("bvh.build.right", n - 1, wp.int32)
            first = b.ensure("bvh.build.first", n - 1, wp.int32)
            last = b.ensure("bvh.build.last", n - 1, wp.int32)
            prefix = b.ensure("bvh.build.prefix", n - 1, wp.int32)
            parent = b.ensure("bvh.build.parent", 2 * n - 1, wp.int32)
            link_radix_tree(self.leaf_key, self.leaf_count, n, parent, first, prefix, children=(left, right), last=last)
            self._link(left, right, first, last)
        self._cuts.clear()

    def _link_shape(self) -> None:
        """Upload the given shape (its leaves' faces, children and leaf ranges) and link it, once (its first build,
        which is never part of a graph: it copies from the host)."""
        n = self.face_count
        self.leaf_face.assign(self.shape.order)
        wp.launch(_invert_order, dim=n, inputs=[self.leaf_face], outputs=[self.face_leaf], device=self.device)
        links = {name: self._buffers.ensure(f"bvh.build.{name}", n - 1, wp.int32)
                 for name in ("left", "right", "first", "last")}
        for name, array in links.items():
            array.assign(getattr(self.shape, name))
        self._link(links["left"], links["right"], links["first"], links["last"])
        self._shape_linked = True

    def _link(self, left: wp.array, right: wp.array, first: wp.array, last: wp.array) -> None:
        """Link the slots and the 4-wide view from a binary tree's children and leaf ranges (left and right are
        taken as the view's scratch)."""
        n = self.face_count
        b = self._buffers
        # each slot's first sorted triangle and count, and each node's slot in its parent: the view's link reads
        # them, and nothing after it
        slot_first = b.ensure("bvh.build.slot_first", 2 * (n - 1), wp.int32)
        slot_count = b.ensure("bvh.build.slot_count", 2 * (n - 1), wp.int32)
        parent_slot = b.ensure("bvh.build.parent_slot", 2 * n - 1, wp.int32)
        parent_slot.fill_(-1)
        wp.launch(
            _link_slots,
            dim=n - 1,
            inputs=[left, right, first, last, n - 1],
            outputs=[self.slot_child, slot_first, slot_count, parent_slot],
            device=self.device,
        )
        # the tree's left and right links are spent once the slots hold them: the 4-wide view's link takes them
        # for its own per-node scratch
        self.wide.link(self.slot_child, slot_count, slot_first, parent_slot, left, right)
        self._cuts.clear()

    def give_back_build(self) -> bool:
        """Free what only a build uses (4.9 MB for the bunny), for an object whose frames no longer rebuild:
        its owner calls this on a frame that keeps the domain, once the last frame's work is done, so objects
        whose every frame moves the domain keep them and allocate nothing per frame. Whether anything was freed."""
        return self._buffers.release("bvh.build.")

    def refit(self, vertices: wp.array, faces: wp.array) -> None:
        """Recompute every box in the 4-wide view (and the winding moments) bottom-up from the current vertices."""
        w = self.wide
        w.arrivals.zero_()
        wp.launch(
            _refit,
            dim=self.face_count,
            inputs=[vertices, faces, self.leaf_face, w.leaf_entry, w.up, w.node, w.child, self.slot_child,
                    self.internal_count, 1 if self.with_moments else 0],
            outputs=[self.triangles, w.planes, w.arrivals, self.node_moments],
            device=self.device,
        )
        if self.rim_count:
            wp.launch(_rim_corners, dim=self.rim_count, inputs=[vertices, self.rim_faces], outputs=[self.rim],
                      device=self.device)

    def measure_spread(self, side: float, *, linked: bool) -> None:
        """Queue the two sums of the leaf spread (`spread_units` divides them): over consecutive leaves, the distances
        between their centroids, and the diagonals of their boxes, in fixed point of a domain of `side` (so that the
        sums do not depend on the order threads add them in); kept as the linking frame's too where the frame
        `linked` the tree. A tree linked on Morton codes keeps neighbouring triangles in neighbouring leaves;
        refitted to a frame far from the one it was linked on (a violent frame's triangles, then the calm mesh
        again), its neighbouring leaves lie far apart and its boxes overlap, which slows every walk."""
        self.leaf_spread[0:2].zero_()
        wp.launch(_leaf_spread, dim=SPREAD_THREADS, inputs=[self.triangles, self.face_count, 2.0**32 / side],
                  outputs=[self.leaf_spread], device=self.device)
        if linked:
            wp.launch(_keep_linked_spread, dim=1, inputs=[self.leaf_spread], device=self.device)

    def cut(self, levels: int) -> wp.array:
        """The 4-wide view's entries `cut_bits(levels)` binary levels below the root (2^cut_bits(levels) of them, -1
        where none lies that deep), whose subtrees together hold every triangle once; kept until the next build,
        as only the tree's shape decides them."""
        bits = cut_bits(levels)
        if bits not in self._cuts:
            cut = self._buffers.ensure(f"bvh.cut.{bits}", 1 << bits, wp.int32)
            if self.internal_count > 0:
                wp.launch(_cut_entries, dim=1 << bits, inputs=[self.view(), bits // 2], outputs=[cut],
                          device=self.device)
            else:
                cut.fill_(-1)
            self._cuts[bits] = cut
        return self._cuts[bits]

    def view(self, cut_slot: int = 0) -> BvhView:
        """The tree as kernels take it; its winding walks count their cuts in `winding_cuts[cut_slot]`."""
        return self._views.view(dict(
            internal_count=self.internal_count, code_levels=self.code_levels, index_bits=self.index_bits,
            slot_child=self.slot_child, triangles=self.triangles, leaf_face=self.leaf_face, face_leaf=self.face_leaf,
            leaf_key=self.leaf_key, key_leaf=self.key_leaf, keys_in_leaf_order=1 if self.shape is None else 0,
            far_field=self.far_field, winding_budget=self.winding_budget, soup_area=self.soup_area,
            winding_cuts=self.winding_cuts, leaf_spread=self.leaf_spread, cut_slot=cut_slot, fat_area=self.fat_area,
            node_moments=self.node_moments, wide_planes=self.wide.planes, wide_child=self.wide.child,
            wide_first=self.wide.first, rim=self.rim, rim_count=self.rim_count), slot=cut_slot)

    def leaf_faces(self) -> np.ndarray:
        return self.leaf_face.numpy()


def cut_bits(levels: int) -> int:
    """The depth, in binary levels, of the cut `Bvh.cut(levels)` gives: `levels` rounded up to even, as the 4-wide
    view's entries lie two binary levels below their node."""
    return 2 * ((levels + 1) // 2)


class WideTree:
    """The 4-wide view of a Bvh's binary tree, which the searches walk and which holds the tree's boxes (see the
    module's docstring).

    Its nodes are the binary internal nodes at even depth, numbered in the binary tree's order. Node k's entry j
    is one of the binary slots two levels down (or one, where the slot holds a single triangle), in the binary
    tree's order: a child's two entries follow each other. Every even-depth node but the root has a parent at
    odd depth, which has at most two children, so with E even-depth and O odd-depth internal nodes, E <= 1 + 2 O
    and E + O = n - 1 give E <= (2n - 1) / 3: the arrays are sized for that (the count is not read back at a
    build) and hold NO_CHILD past it. The view takes a child of at most LEAF_SIZE triangles as a single triangle,
    which it is while LEAF_SIZE is 1.

    The refit climbs it: each leaf's thread writes its box into its entry (`leaf_entry`), and the last entry of a
    node to arrive merges the node's box and writes it into the node's own entry in its parent (`up`).
    """

    def __init__(self, face_count: int, buffers: DeviceBuffers):
        self.internal_count = face_count - 1
        self.capacity = (2 * face_count - 1) // 3 + 1
        self.device = buffers.device
        b = buffers
        self.child = b.array("bvh.wide.child", 4 * self.capacity, wp.int32)
        self.first = b.array("bvh.wide.first", self.capacity, wp.int32)
        self.planes: wp.array | None = None  # the boxes, which the Bvh allocates with what else a refit writes
        # the refit's: each node's binary node, the entry that holds it in its parent (-1 for the root), each
        # leaf's entry, and how many of each node's entries have arrived
        self.node = b.array("bvh.wide.node", self.capacity, wp.int32)
        self.up = b.array("bvh.wide.up", self.capacity, wp.int32)
        self.leaf_entry = b.array("bvh.wide.leaf_entry", face_count, wp.int32)
        self.arrivals = b.array("bvh.wide.arrivals", self.capacity, wp.int32)

    def link(self, slot_child: wp.array, slot_count: wp.array, slot_first: wp.array, parent_slot: wp.array,
             even: wp.array, rank: wp.array) -> None:
        """Number the even-depth nodes (in the binary tree's order) and link each one's entries, whose boxes are
        left empty until a refit; `even` and `rank` are scratch of one int32 per internal node."""
        internal = self.internal_count
        self.child.fill_(NO_CHILD)
        self.up.fill_(-1)
        wp.launch(_empty_planes, dim=6 * self.capacity, inputs=[self.planes], device=self.device)
        wp.launch(_even_depth, dim=internal, inputs=[parent_slot], outputs=[even], device=self.device)
        wp.utils.array_scan(even, rank, inclusive=False)
        wp.launch(_link_wide, dim=internal, inputs=[even, rank, slot_child, slot_count, slot_first],
                  outputs=[self.child, self.first, self.node, self.up, self.leaf_entry], device=self.device)


@wp.kernel(enable_backward=False)
def _even_depth(parent_slot: wp.array(dtype=wp.int32), even: wp.array(dtype=wp.int32)):
    """1 where internal node i lies an even number of levels below the root."""
    i = wp.tid()
    depth = int(0)
    slot = parent_slot[i]
    while slot >= 0:
        depth += 1
        slot = parent_slot[slot // 2]
    even[i] = 1 - (depth & 1)


@wp.kernel(enable_backward=False)
def _link_wide(even: wp.array(dtype=wp.int32), rank: wp.array(dtype=wp.int32), slot_child: wp.array(dtype=wp.int32),
               slot_count: wp.array(dtype=wp.int32), slot_first: wp.array(dtype=wp.int32),
               wide_child: wp.array(dtype=wp.int32), wide_first: wp.array(dtype=wp.int32),
               wide_node: wp.array(dtype=wp.int32), wide_up: wp.array(dtype=wp.int32),
               leaf_entry: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if even[i] == 0:
        return
    k = rank[i]
    wide_node[k] = i
    entry = 4 * k
    for side in range(2):
        slot = 2 * i + side
        if slot_count[slot] <= LEAF_SIZE:
            _link_entry(entry, slot, rank, slot_child, slot_count, slot_first, wide_child, wide_first, wide_up,
                        leaf_entry)
            entry += 1
        else:
            inner = slot_child[slot]
            for inner_side in range(2):
                _link_entry(entry, 2 * inner + inner_side, rank, slot_child, slot_count, slot_first, wide_child,
                            wide_first, wide_up, leaf_entry)
                entry += 1


@wp.func
def _link_entry(entry: int, slot: int, rank: wp.array(dtype=wp.int32), slot_child: wp.array(dtype=wp.int32),
                slot_count: wp.array(dtype=wp.int32), slot_first: wp.array(dtype=wp.int32),
                wide_child: wp.array(dtype=wp.int32), wide_first: wp.array(dtype=wp.int32),
                wide_up: wp.array(dtype=wp.int32), leaf_entry: wp.array(dtype=wp.int32)):
    """Entry `entry` of the view holds binary slot `slot`: a single triangle, or an even-depth node."""
    first = slot_first[slot]
    if slot_count[slot] <= LEAF_SIZE:
        wide_child[entry] = -1 - first
        leaf_entry[first] = entry
    else:
        child = rank[slot_child[slot]]
        wide_child[entry] = child
        wide_first[child] = first
        wide_up[child] = entry


@wp.kernel(enable_backward=False)
def _empty_planes(planes: wp.array(dtype=wp.vec4)):
    """Every entry's box empty (lower above upper, so no point comes within reach of it): an absent entry's stays so."""
    i = wp.tid()
    if i % 6 < 3:
        planes[i] = wp.vec4(EMPTY_BOX)
    else:
        planes[i] = wp.vec4(-EMPTY_BOX)


def link_radix_tree(
    keys: wp.array,
    count: wp.array,
    capacity: int,
    parent: wp.array,
    first: wp.array,
    prefix: wp.array,
    *,
    children: tuple[wp.array, wp.array] | None = None,
    last: wp.array | None = None,
) -> None:
    """Karras's parallel radix tree over the first count[0] (at most `capacity`) sorted, unique int64 keys;
    the count stays on the device.

    Fills, for internal node i: the first key under it `first[i]` (and the last, `last[i]`, where asked), its
    common-prefix length in code bits `prefix[i]`, and its `children` (left, right; leaf k as count - 1 + k) where
    asked; and `parent` of every node (-1 for the root). The octree asks for neither children nor last: its
    stage leaves out their two arrays of the cells' count.
    """
    parent.fill_(-1)
    if capacity > 1:
        left, right = children if children is not None else (parent, parent)  # not written where not asked for
        wp.launch(
            _link_radix_tree,
            dim=capacity - 1,
            inputs=[keys, count, capacity, 1 if children is not None else 0, 1 if last is not None else 0],
            outputs=[parent, left, right, first, prefix, last if last is not None else first],
            device=keys.device,
        )


@wp.func
def spatial_seed(bvh: BvhView, p: wp.vec3, origin: wp.vec3, inv_side: float) -> int:
    """A leaf near p: the one whose Morton key is nearest p's own, found by binary search."""
    resolution = 1 << bvh.code_levels
    cell = quantize(p, origin, float(resolution) * inv_side, resolution)
    key = morton3(cell[0], cell[1], cell[2]) << wp.int64(bvh.index_bits)
    lo = int(0)
    hi = bvh.internal_count  # leaf count - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if bvh.leaf_key[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if bvh.keys_in_leaf_order != 0:
        return lo
    return bvh.key_leaf[lo]


@wp.func
def leaf_triangle(bvh: BvhView, leaf: int):
    """Corners (a, b, c) of the triangle at sorted leaf `leaf`."""
    a = load_vec4(bvh.triangles, 3 * leaf)
    b = load_vec4(bvh.triangles, 3 * leaf + 1)
    c = load_vec4(bvh.triangles, 3 * leaf + 2)
    return wp.vec3(a[0], a[1], a[2]), wp.vec3(b[0], b[1], b[2]), wp.vec3(c[0], c[1], c[2])


SPREAD_THREADS = 4096  # threads of _leaf_spread, each one atomic add a sum (one per leaf waits on one address)


@wp.func
def _packed_centroid(triangles: wp.array(dtype=wp.vec4), leaf: int) -> wp.vec3:
    a, b, c = triangles[3 * leaf], triangles[3 * leaf + 1], triangles[3 * leaf + 2]
    return wp.vec3(a[0] + b[0] + c[0], a[1] + b[1] + c[1], a[2] + b[2] + c[2]) / 3.0


@wp.kernel(enable_backward=False)
def _leaf_spread(triangles: wp.array(dtype=wp.vec4), leaf_count: int, unit: float, sums: wp.array(dtype=wp.int64)):
    """Thread t adds up every SPREAD_THREADS-th leaf from t: the distance from its centroid to the next leaf's, into
    sums[0], and its box's diagonal, into sums[1], in units of 1 / `unit`."""
    gap = float(0.0)
    size = float(0.0)
    k = wp.tid()
    while k < leaf_count:
        a, b, c = triangles[3 * k], triangles[3 * k + 1], triangles[3 * k + 2]
        lo = wp.min(wp.min(wp.vec3(a[0], a[1], a[2]), wp.vec3(b[0], b[1], b[2])), wp.vec3(c[0], c[1], c[2]))
        hi = wp.max(wp.max(wp.vec3(a[0], a[1], a[2]), wp.vec3(b[0], b[1], b[2])), wp.vec3(c[0], c[1], c[2]))
        size += wp.length(hi - lo)
        if k + 1 < leaf_count:
            gap += wp.length(_packed_centroid(triangles, k + 1) - _packed_centroid(triangles, k))
        k += SPREAD_THREADS
    wp.atomic_add(sums, 0, wp.int64(gap * unit))
    wp.atomic_add(sums, 1, wp.int64(size * unit))


@wp.kernel(enable_backward=False)
def _keep_linked_spread(sums: wp.array(dtype=wp.int64)):
    sums[2] = sums[0]
    sums[3] = sums[1]


SPREAD_UNIT = wp.constant(256)  # a leaf spread's unit in the frame's report, 1 / SPREAD_UNIT
_RELINK_SPREAD = wp.constant(RELINK_SPREAD)
_RELINK_FLOOR_UNITS = wp.constant(int(RELINK_SPREAD_FLOOR * 256))
_RERUN_UNITS = wp.constant(int(RERUN_SPREAD * 256))


@wp.func
def spread_units(gaps: wp.int64, sizes: wp.int64) -> int:
    """The leaf spread (gaps over sizes, at most 1e6; 0 where nothing was measured) in 1 / SPREAD_UNIT."""
    spread = float(0.0)
    if sizes > wp.int64(0):
        spread = wp.min(float(gaps) / float(sizes), 1.0e6)
    return int(spread * float(SPREAD_UNIT))


TREE_FITS = wp.constant(0)
TREE_DUE = wp.constant(1)  # to be linked again by the next frame
TREE_MISFITS = wp.constant(2)  # due, and so far off that a frame whose walk was cut runs again at once


@wp.func
def tree_fit(sums: wp.array(dtype=wp.int64)) -> int:
    """How the tree fits this frame, from Bvh.measure_spread's sums: TREE_DUE past RELINK_SPREAD times the linking
    frame's spread (or the floor), TREE_MISFITS where it also passes RERUN_SPREAD, else TREE_FITS. The frame's report
    carries it to the host (`DistanceField._relink_due`, `_rebuild`), and the winding walks read it: one rule for
    both."""
    spread = spread_units(sums[0], sums[1])
    linked = wp.max(spread_units(sums[2], sums[3]), _RELINK_FLOOR_UNITS)
    if float(spread) <= _RELINK_SPREAD * float(linked):
        return TREE_FITS
    return wp.where(spread > _RERUN_UNITS, TREE_MISFITS, TREE_DUE)


@wp.func
def tree_misfits(bvh: BvhView) -> bool:
    """Whether the tree misfits this frame so badly that the frame runs again on a tree linked on itself once a walk
    is cut (`tree_fit`)."""
    return tree_fit(bvh.leaf_spread) == TREE_MISFITS


@wp.func
def leaf_distance_sq(bvh: BvhView, leaf: int, p: wp.vec3) -> float:
    a, b, c = leaf_triangle(bvh, leaf)
    return triangle_distance_sq(p, a, b, c)


@wp.func
def _xyz(v: wp.vec4) -> wp.vec3:
    return wp.vec3(v[0], v[1], v[2])


@wp.func
def beats(d_sq: float, leaf: int, best_sq: float, best_leaf: int) -> bool:
    """Whether `leaf` at squared distance d_sq beats the best so far: nearer, or as near with a lower index.
    Faces tie wherever a feature they share is nearest (off a convex mesh's vertices and edges, a whole
    region of space ties), so ties go to the lowest leaf, and which face a search reports does not depend on
    the bound it started from (coherence, a corner's faces). A best_leaf of -1 (nothing within the band)
    takes no tie."""
    return d_sq < best_sq or (d_sq == best_sq and leaf < best_leaf)


@wp.func
def leaf_distance_held_to_box_sq(bvh: BvhView, leaf: int, p: wp.vec3) -> float:
    """Squared distance from p to the triangle at sorted leaf `leaf`, raised to its bounding box's where it
    rounds below that. Exactly, a triangle is never nearer than its box; in float32, far from the mesh (beyond
    about 30 domain sides), it can be by an ulp or two. Every box in the BVH holds the triangle's box, and a
    box's rounded distance only falls as the box grows, so no leaf's value is below any box above it, and a
    search that prunes by boxes finds the least value however it starts."""
    a, b, c = leaf_triangle(bvh, leaf)
    d_sq = triangle_distance_sq(p, a, b, c)
    return wp.max(d_sq, box_distance_sq(p, wp.min(wp.min(a, b), c), wp.max(wp.max(a, b), c)))


@wp.func
def _plane_gaps(p: float, lower: wp.vec4, upper: wp.vec4) -> wp.vec4:
    """How far coordinate p lies outside each of four boxes' [lower, upper] along one axis."""
    return wp.vec4(wp.max(wp.max(lower[0] - p, p - upper[0]), 0.0), wp.max(wp.max(lower[1] - p, p - upper[1]), 0.0),
                   wp.max(wp.max(lower[2] - p, p - upper[2]), 0.0), wp.max(wp.max(lower[3] - p, p - upper[3]), 0.0))


@wp.func
def entry_distances_sq(bvh: BvhView, p: wp.vec3, node: int) -> wp.vec4:
    """Squared distances from p to the four boxes of 4-wide node `node` (huge for an absent entry's empty box)."""
    gap_x = _plane_gaps(p[0], load_vec4(bvh.wide_planes, 6 * node), load_vec4(bvh.wide_planes, 6 * node + 3))
    gap_y = _plane_gaps(p[1], load_vec4(bvh.wide_planes, 6 * node + 1), load_vec4(bvh.wide_planes, 6 * node + 4))
    gap_z = _plane_gaps(p[2], load_vec4(bvh.wide_planes, 6 * node + 2), load_vec4(bvh.wide_planes, 6 * node + 5))
    d = wp.vec4()
    for j in range(4):
        d[j] = gap_x[j] * gap_x[j] + gap_y[j] * gap_y[j] + gap_z[j] * gap_z[j]
    return d


def _wide_searches(past_tied_boxes: bool, budgeted: bool = False):
    """The nearest-leaf search over the 4-wide view, built three ways. With `past_tied_boxes` a box exactly as far
    as the best so far is passed over when its first leaf comes after the best's, since none of its leaves can win
    the tie (`beats`). Seen from far enough (1e8 sizes away) every face ties in float32, and without it a search
    visits every face: 0.8 ms a point for 20K faces on the CPU, 3 us with it (fifteenth outside check). Passing
    over a tied box is exact only if no leaf under it is valued below the box, so this search values a leaf by
    `leaf_distance_held_to_box_sq`; by the plain triangle distance, which beyond about 30 domain sides can round an
    ulp or two below its box's, 403 of 4,000 searches off a box named another face than the least (review,
    sixteenth stop). The planes give a box the distance `box_distance_sq` gives it, in the same order of
    operations, so that holds here too. The corner searches, which never meet such ties in bulk and never look
    from that far, take the search without either: the extra test made the binary walk 15% slower on the H100
    (2026-11-23); the queries take the search with both (on the 4-wide view since 2026-11-28).

    Only a `budgeted` walk reads its `budget` (and counts its visits): the corner searches that hand their long
    walks on to subtree searches (`SearchSplit`). Every other walk runs to its end, and without the count and its
    test the engine's corner-search kernel took 2 to 4% less time on an H200 (2026-12-02, probe_search_variants).
    """

    def leaf_sq(bvh: BvhView, leaf: int, p: wp.vec3) -> float:
        if wp.static(past_tied_boxes):
            return leaf_distance_held_to_box_sq(bvh, leaf, p)
        return leaf_distance_sq(bvh, leaf, p)

    leaf_sq = wp.func(leaf_sq, module="unique")

    def may_hold(bvh: BvhView, box_sq: float, child: int, best_sq: float, best_leaf: int) -> bool:
        """Whether an entry holding `child` (a 4-wide node, or -1 - leaf), whose box lies box_sq from the point,
        may hold a leaf that beats the best: a box nearer than it, or exactly as near (with a leaf of lower index
        under it)."""
        if wp.static(past_tied_boxes):
            if box_sq == best_sq:
                first = -1 - child
                if child >= 0:
                    first = bvh.wide_first[child]
                return first < best_leaf
        return box_sq <= best_sq

    may_hold = wp.func(may_hold, module="unique")

    def nearest_under(bvh: BvhView, p: wp.vec3, root: int, best_leaf: int, best_sq: float, budget: int):
        """Nearest leaf under 4-wide node `root` of those that beat (best_sq, best_leaf) (see `beats`), in at
        most `budget` binary node visits (a 4-wide visit counts two) where `budgeted`, however many it takes
        otherwise: (best_leaf, best_sq, finished). It opens
        every box that may hold a better leaf, so it finds the least (value, leaf) whatever the order it walks
        in. Triangles are tested first, then the nodes pushed farthest first, so that the nearest is walked next.
        A node pushed before the best came to tie with its box is still opened (its entries are tested against
        the tie), which only costs a visit."""
        nodes = wide_stack_int()
        bounds = wide_stack_float()
        nodes[0] = root
        bounds[0] = 0.0
        top = int(1)
        visits = int(0)
        while top > 0:
            top -= 1
            if bounds[top] > best_sq:
                continue
            if wp.static(budgeted):
                if visits >= budget:
                    return best_leaf, best_sq, False
                visits += 2
            node = nodes[top]
            d = entry_distances_sq(bvh, p, node)
            child = wp.vec4i()
            for j in range(4):
                child[j] = bvh.wide_child[4 * node + j]
            for j in range(4):
                if child[j] < 0 and may_hold(bvh, d[j], child[j], best_sq, best_leaf):
                    leaf = -1 - child[j]
                    d_sq = leaf_sq(bvh, leaf, p)
                    if beats(d_sq, leaf, best_sq, best_leaf):
                        best_sq = d_sq
                        best_leaf = leaf
            for j in range(4):
                if child[j] >= 0 and child[j] != NO_CHILD:
                    if not may_hold(bvh, d[j], child[j], best_sq, best_leaf):
                        child[j] = NO_CHILD
            for _push in range(4):
                far = int(-1)
                far_d = float(-1.0)
                for j in range(4):
                    if child[j] >= 0 and child[j] != NO_CHILD and d[j] > far_d:
                        far = j
                        far_d = d[j]
                if far >= 0:
                    nodes[top] = child[far]
                    bounds[top] = far_d
                    top += 1
                    child[far] = NO_CHILD
        return best_leaf, best_sq, True

    suffix = ("_past_ties" if past_tied_boxes else "") + ("_budgeted" if budgeted else "")
    nearest_under.__name__ = nearest_under.__qualname__ = "nearest_under" + suffix
    nearest_under = wp.func(nearest_under, module="unique")

    def nearest_leaf_wide(bvh: BvhView, p: wp.vec3, best_leaf: int, best_sq: float, budget: int):
        """`nearest_under` the root: the nearest leaf of the whole tree that beats (best_sq, best_leaf)."""
        if bvh.internal_count == 0:
            d_sq = leaf_sq(bvh, 0, p)
            if beats(d_sq, 0, best_sq, best_leaf):
                return 0, d_sq, True
            return best_leaf, best_sq, True
        best_leaf, best_sq, finished = nearest_under(bvh, p, 0, best_leaf, best_sq, budget)
        return best_leaf, best_sq, finished

    nearest_leaf_wide.__name__ = nearest_leaf_wide.__qualname__ = "nearest_leaf_wide" + suffix
    return nearest_under, wp.func(nearest_leaf_wide, module="unique")


# the corner searches' (whole, or budgeted where long walks are handed on) and the queries' (see `_wide_searches`
# for why they differ)
_nearest_under, nearest_leaf_wide = _wide_searches(past_tied_boxes=False)
_, nearest_leaf_budgeted = _wide_searches(past_tied_boxes=False, budgeted=True)
_, nearest_leaf_past_ties = _wide_searches(past_tied_boxes=True)


@wp.func
def nearest_in_entry(bvh: BvhView, p: wp.vec3, entry: int, best_leaf: int, best_sq: float):
    """Nearest leaf under the 4-wide view's entry `entry` (4 k + j: node k's entry j) that beats (best_sq,
    best_leaf), however long the walk: (best_leaf, best_sq)."""
    node = entry // 4
    if entry_distances_sq(bvh, p, node)[entry - 4 * node] > best_sq:
        return best_leaf, best_sq
    child = bvh.wide_child[entry]
    if child < 0:
        leaf = -1 - child
        d_sq = leaf_distance_sq(bvh, leaf, p)
        if beats(d_sq, leaf, best_sq, best_leaf):
            return leaf, d_sq
        return best_leaf, best_sq
    best_leaf, best_sq, finished = _nearest_under(bvh, p, child, best_leaf, best_sq, UNLIMITED_VISITS)
    return best_leaf, best_sq


@wp.kernel(enable_backward=False)
def _cut_entries(bvh: BvhView, levels: int, cut: wp.array(dtype=wp.int32)):
    """Entry k of the 4-wide view's cut `levels` of its levels deep (4^levels of them): the entry reached by
    taking k's base-4 digits as entries from the root, -1 where that runs out of entries (a single triangle
    above that depth keeps only the first k under it)."""
    k = wp.tid()
    node = int(0)
    for level in range(levels):
        entry = 4 * node + ((k >> (2 * (levels - 1 - level))) & 3)
        child = bvh.wide_child[entry]
        if child == NO_CHILD:
            cut[k] = -1
            return
        if level == levels - 1:
            cut[k] = entry
            return
        if child < 0:
            # a single triangle stops the descent: only the first k under it keeps it
            if (k & ((1 << (2 * (levels - 1 - level))) - 1)) != 0:
                entry = -1
            cut[k] = entry
            return
        node = child
    cut[k] = -1  # no levels: no entry


@wp.func
def leaf_moments(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """A triangle's centroid with the radius of its farthest corner, and its area-weighted normal with its
    area (the first two of the moments in BvhView.node_moments; its first moment about the centroid is 0)."""
    mid = (a + b + c) / 3.0
    n = 0.5 * wp.cross(b - a, c - a)
    centre_radius = wp.vec4(mid[0], mid[1], mid[2],
                            wp.max(wp.max(wp.length(a - mid), wp.length(b - mid)), wp.length(c - mid)))
    return centre_radius, wp.vec4(n[0], n[1], n[2], wp.length(n))


@wp.func
def _far_field(bvh: BvhView, node: int, u: wp.vec3, dist: float) -> float:
    """4 pi times the winding number of a far internal node at distance `dist` along unit `u` (from the
    point to the node's centre): the dipole n.u / d^2, plus the first moment's (tr S - 3 u.S.u) / d^3."""
    s0 = load_vec4(bvh.node_moments, 4 * node + 2)
    s1 = load_vec4(bvh.node_moments, 4 * node + 3)
    su = wp.vec3(
        s0[0] * u[0] + s0[3] * u[1] + s1[0] * u[2],
        s0[3] * u[0] + s0[1] * u[1] + s1[1] * u[2],
        s1[0] * u[0] + s1[1] * u[1] + s0[2] * u[2],
    )
    first = (s0[0] + s0[1] + s0[2] - 3.0 * wp.dot(u, su)) / dist
    return (wp.dot(_xyz(load_vec4(bvh.node_moments, 4 * node + 1)), u) + first) / (dist * dist)


@wp.func
def is_soup(bvh: BvhView) -> bool:
    """Whether the frame's surface is a soup: more than `bvh.soup_area` times the area of the sphere its root bounds
    (SOUP_AREA). A closed convex surface inside the sphere has at most the sphere's area; large triangles thrown across
    each other pile up many times it."""
    radius = load_vec4(bvh.node_moments, 0)[3]
    return load_vec4(bvh.node_moments, 1)[3] > bvh.soup_area * 4.0 * wp.pi * radius * radius


def _winding_number_function(careful: bool):
    """The winding number's walk; returns (w, whether a near triangle's float32 solid angle cancelled, so
    that w may be wrong). `careful`: such solid angles are worked out in float64 (`solid_angle_careful`),
    and none is left cancelled; otherwise float32 throughout, whose registers the corners' winding kernel
    can afford."""

    def winding_number(bvh: BvhView, p: wp.vec3):
        """Generalised winding number of p: exact solid angles near p, two-term expansions far away (Barill 2018).
        In a soup (`is_soup`), or on a tree that misfits the frame (`tree_misfits`: the frame then runs again), a
        walk opens at most `bvh.winding_budget` fat internal nodes (of more than `bvh.fat_area` times their disc's
        area: a soup's piled triangles; a thin node, of long thin triangles however many layers deep, is opened
        uncounted, but on a misfit tree every node counts); the nodes still waiting then take their expansion where
        p lies beyond their radius and are left out where it lies within, and the walk counts itself in
        `bvh.winding_cuts` (at `bvh.cut_slot`). Elsewhere a walk runs whole, however many nodes it opens. The budget
        is spent as a node is pushed, not as it is opened, so that it costs an unbound walk nothing (the first form,
        which marked thin nodes on the stack and counted them as they were opened, made the bunny's update 0.087 ms
        longer on an H200)."""
        total = float(0.0)
        cancelled = bool(False)
        if bvh.internal_count == 0:
            a, b, c = leaf_triangle(bvh, 0)  # a single triangle, and no tree
            if wp.static(careful):
                total = solid_angle_careful(p, a, b, c)
            else:
                total, cancelled = solid_angle_checked(p, a, b, c)
            return total * _INV_FOUR_PI, cancelled
        nodes = stack_int()
        nodes[0] = 0
        count = int(1)
        budget = bvh.winding_budget
        # on a misfit tree every node counts: there a calm frame's nodes gather small triangles from far apart, thin
        # by their area, and the walks must meet the budget for the frame to run again on a tree of its own
        misfit = tree_misfits(bvh)
        bounded = misfit or is_soup(bvh)
        thin_free = bounded and not misfit
        while count > 0 and (budget > 0 or not bounded):
            count -= 1
            slot = 2 * nodes[count]
            for side in range(2):
                child = bvh.slot_child[slot + side]
                if child >= bvh.internal_count:  # a single triangle: its dipole far away, else its solid angle
                    leaf = child - bvh.internal_count
                    a, b, c = leaf_triangle(bvh, leaf)
                    centre_radius, normal_area = leaf_moments(a, b, c)
                    offset = _xyz(centre_radius) - p
                    dist = wp.length(offset)
                    if dist > bvh.far_field * centre_radius[3]:
                        total += wp.dot(_xyz(normal_area), offset / dist) / (dist * dist)
                    elif wp.static(careful):
                        total += solid_angle_careful(p, a, b, c)
                    else:
                        angle, near_cancelled = solid_angle_checked(p, a, b, c)
                        total += angle
                        cancelled = cancelled or near_cancelled
                else:
                    centre_radius = load_vec4(bvh.node_moments, 4 * child)
                    offset = _xyz(centre_radius) - p
                    dist = wp.length(offset)
                    if dist > bvh.far_field * centre_radius[3]:
                        total += _far_field(bvh, child, offset / dist, dist)
                    else:
                        if bounded:  # the budget is spent as nodes are pushed, so that an unbound walk pays nothing
                            if thin_free:
                                area = load_vec4(bvh.node_moments, 4 * child + 1)[3]
                                if area > bvh.fat_area * wp.pi * centre_radius[3] * centre_radius[3]:
                                    budget -= 1
                            else:
                                budget -= 1
                        nodes[count] = child
                        count += 1
        if count > 0:  # the budget is spent (a soup of large triangles): what waits is summed roughly, or left out
            wp.atomic_add(bvh.winding_cuts, bvh.cut_slot, 1)
            while count > 0:
                count -= 1
                centre_radius = load_vec4(bvh.node_moments, 4 * nodes[count])
                offset = _xyz(centre_radius) - p
                dist = wp.length(offset)
                if dist > centre_radius[3]:
                    total += _far_field(bvh, nodes[count], offset / dist, dist)
        return total * _INV_FOUR_PI, cancelled

    winding_number.__name__ = winding_number.__qualname__ = "winding_number_careful" if careful else "winding_number"
    return wp.func(winding_number)


# the corners' (float32 throughout, telling where it cancelled) and everything else's (queries, the overlap
# check, orientation)
winding_number = _winding_number_function(False)
winding_number_careful = _winding_number_function(True)


@wp.func
def rim_corrected(bvh: BvhView, p: wp.vec3, w: float) -> float:
    """A walk's winding number w of p made exact by the rim's fans C: the mesh and C close each other's boundary,
    so w + w_C is a whole number k, and the oracle's w is k - w_C, with w_C summed over C's solid angles in full
    (float64 where float32 cancels). Where w + w_C is farther than RIM_TRUST from a whole number (a walk that
    erred that much, or p on a fan), w is returned as it came."""
    rim = float(0.0)
    for t in range(bvh.rim_count):
        rim += solid_angle_careful(p, bvh.rim[3 * t], bvh.rim[3 * t + 1], bvh.rim[3 * t + 2])
    rim *= _INV_FOUR_PI
    closed = w + rim
    whole = wp.round(closed)
    if wp.abs(closed - whole) < _RIM_TRUST:
        return whole - rim
    return w


@wp.kernel(enable_backward=False)
def _rim_corners(vertices: wp.array(dtype=wp.vec3), rim_faces: wp.array(dtype=wp.vec3i), rim: wp.array(dtype=wp.vec3)):
    t = wp.tid()
    fan = rim_faces[t]
    rim[3 * t] = vertices[fan[0]]
    rim[3 * t + 1] = vertices[fan[1]]
    rim[3 * t + 2] = vertices[fan[2]]


@wp.kernel(enable_backward=False)
def _triangle_keys(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    origin: wp.vec3,
    inv_cell: float,
    resolution: int,
    index_bits: int,
    keys: wp.array(dtype=wp.int64),
    face_ids: wp.array(dtype=wp.int32),
):
    f = wp.tid()
    tri = faces[f]
    centroid = (vertices[tri[0]] + vertices[tri[1]] + vertices[tri[2]]) / 3.0
    cell = quantize(centroid, origin, inv_cell, resolution)
    keys[f] = (morton3(cell[0], cell[1], cell[2]) << wp.int64(index_bits)) | wp.int64(f)
    face_ids[f] = f


@wp.kernel(enable_backward=False)
def _leaf_of_key(key_face: wp.array(dtype=wp.int32), face_leaf: wp.array(dtype=wp.int32),
                 key_leaf: wp.array(dtype=wp.int32)):
    k = wp.tid()
    key_leaf[k] = face_leaf[key_face[k]]


@wp.kernel(enable_backward=False)
def _invert_order(leaf_face: wp.array(dtype=wp.int32), face_leaf: wp.array(dtype=wp.int32)):
    k = wp.tid()
    face_leaf[leaf_face[k]] = k


@wp.func
def _common_prefix(keys: wp.array(dtype=wp.int64), count: int, i: int, j: int) -> int:
    if j < 0 or j >= count:
        return -1
    return clz64(keys[i] ^ keys[j])


@wp.kernel(enable_backward=False)
def _link_radix_tree(
    keys: wp.array(dtype=wp.int64),
    count_array: wp.array(dtype=wp.int32),
    capacity: int,
    with_children: int,
    with_last: int,
    parent: wp.array(dtype=wp.int32),
    left: wp.array(dtype=wp.int32),
    right: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    prefix: wp.array(dtype=wp.int32),
    last: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    count = wp.min(count_array[0], capacity)
    if i >= count - 1:
        return
    # direction of the node's range, and the prefix its range must exceed
    d = int(1)
    if _common_prefix(keys, count, i, i + 1) < _common_prefix(keys, count, i, i - 1):
        d = -1
    prefix_min = _common_prefix(keys, count, i, i - d)
    length_max = int(2)
    while _common_prefix(keys, count, i, i + length_max * d) > prefix_min:
        length_max *= 2
    length = int(0)
    step = length_max // 2
    while step >= 1:
        if _common_prefix(keys, count, i, i + (length + step) * d) > prefix_min:
            length += step
        step = step // 2
    j = i + length * d
    node_prefix = _common_prefix(keys, count, i, j)
    # binary search for the split: the last key sharing more than node_prefix bits with keys[i]
    split = int(0)
    divisor = int(2)
    step = (length + divisor - 1) // divisor
    while step >= 1:
        if _common_prefix(keys, count, i, i + (split + step) * d) > node_prefix:
            split += step
        if step == 1:
            break
        divisor *= 2
        step = (length + divisor - 1) // divisor
    gamma = i + split * d + wp.min(d, 0)
    lo = wp.min(i, j)
    hi = wp.max(i, j)
    leaf_base = count - 1
    child_left = gamma
    if lo == gamma:
        child_left = leaf_base + gamma
    child_right = gamma + 1
    if hi == gamma + 1:
        child_right = leaf_base + gamma + 1
    if with_children != 0:
        left[i] = child_left
        right[i] = child_right
    parent[child_left] = i
    parent[child_right] = i
    first[i] = lo
    if with_last != 0:
        last[i] = hi
    prefix[i] = node_prefix - (64 - KEY_TOP_BIT)


@wp.kernel(enable_backward=False)
def _link_slots(
    left: wp.array(dtype=wp.int32),
    right: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    last: wp.array(dtype=wp.int32),
    internal_count: int,
    slot_child: wp.array(dtype=wp.int32),
    slot_first: wp.array(dtype=wp.int32),
    slot_count: wp.array(dtype=wp.int32),
    parent_slot: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    for side in range(2):
        child = left[i]
        if side == 1:
            child = right[i]
        lo = child - internal_count
        hi = lo
        if child < internal_count:
            lo = first[child]
            hi = last[child]
        slot_child[2 * i + side] = child
        slot_first[2 * i + side] = lo
        slot_count[2 * i + side] = hi - lo + 1
        parent_slot[child] = 2 * i + side


@wp.func
def _child_radius(mid: wp.vec3, child_centre: wp.vec3, child_radius: float, lower: wp.vec4, upper: wp.vec4) -> float:
    """A radius around `mid` holding the child: its own ball seen from mid, or its box's farthest corner."""
    far = wp.max(wp.abs(mid - _xyz(lower)), wp.abs(_xyz(upper) - mid))
    return wp.min(wp.length(child_centre - mid) + child_radius, wp.length(far))


@wp.func
def _shifted_moment(s0: wp.vec4, s1: wp.vec4, n: wp.vec4, shift: wp.vec3):
    """A child's symmetric moment about its parent's centre: its own plus sym(n x shift)."""
    return (
        s0 + wp.vec4(n[0] * shift[0], n[1] * shift[1], n[2] * shift[2], 0.5 * (n[0] * shift[1] + n[1] * shift[0])),
        s1 + wp.vec4(0.5 * (n[0] * shift[2] + n[2] * shift[0]), 0.5 * (n[1] * shift[2] + n[2] * shift[1]), 0.0, 0.0),
    )


@wp.func
def _child_moments(child: int, internal_count: int, triangles: wp.array(dtype=wp.vec4),
                   node_moments: wp.array(dtype=wp.vec4)):
    """A child's four winding moments: an internal node's as stored, a triangle's worked out (both read
    from L2: written in this launch)."""
    if child >= internal_count:
        k = 3 * (child - internal_count)
        centre_radius, normal_area = leaf_moments(_xyz(load_coherent_vec4(triangles, k)),
                                                  _xyz(load_coherent_vec4(triangles, k + 1)),
                                                  _xyz(load_coherent_vec4(triangles, k + 2)))
        return centre_radius, normal_area, wp.vec4(0.0), wp.vec4(0.0)
    return (load_coherent_vec4(node_moments, 4 * child), load_coherent_vec4(node_moments, 4 * child + 1),
            load_coherent_vec4(node_moments, 4 * child + 2), load_coherent_vec4(node_moments, 4 * child + 3))


@wp.func
def _merged_moments(centre_radius_l: wp.vec4, normal_l: wp.vec4, s0_l: wp.vec4, s1_l: wp.vec4, lower_l: wp.vec4,
                    upper_l: wp.vec4, centre_radius_r: wp.vec4, normal_r: wp.vec4, s0_r: wp.vec4, s1_r: wp.vec4,
                    lower_r: wp.vec4, upper_r: wp.vec4):
    """A node's winding moments from its two children's moments and boxes."""
    total = normal_l[3] + normal_r[3]
    centre_l = _xyz(centre_radius_l)
    centre_r = _xyz(centre_radius_r)
    mid = 0.5 * (centre_l + centre_r)
    if total > 0.0:
        mid = (normal_l[3] * centre_l + normal_r[3] * centre_r) / total
    radius = wp.max(_child_radius(mid, centre_l, centre_radius_l[3], lower_l, upper_l),
                    _child_radius(mid, centre_r, centre_radius_r[3], lower_r, upper_r))
    l0, l1 = _shifted_moment(s0_l, s1_l, normal_l, centre_l - mid)
    r0, r1 = _shifted_moment(s0_r, s1_r, normal_r, centre_r - mid)
    return wp.vec4(mid[0], mid[1], mid[2], radius), normal_l + normal_r, l0 + r0, l1 + r1


@wp.func
def _entry_box(lower_x: wp.vec4, lower_y: wp.vec4, lower_z: wp.vec4, upper_x: wp.vec4, upper_y: wp.vec4,
               upper_z: wp.vec4, j: int):
    """(lower, upper) of entry j of a 4-wide node, from its six planes; w is 0."""
    return (wp.vec4(lower_x[j], lower_y[j], lower_z[j], 0.0), wp.vec4(upper_x[j], upper_y[j], upper_z[j], 0.0))


@wp.func
def _side_moments(node: int, side: int, entry: int, lower_x: wp.vec4, lower_y: wp.vec4, lower_z: wp.vec4,
                  upper_x: wp.vec4, upper_y: wp.vec4, upper_z: wp.vec4, slot_child: wp.array(dtype=wp.int32),
                  internal_count: int, triangles: wp.array(dtype=wp.vec4), node_moments: wp.array(dtype=wp.vec4)):
    """The moments and box of child `side` of binary node `node`, whose entries in its 4-wide node (whose planes
    are given) start at the `entry`-th: a single triangle (one entry), or a binary node between it and two
    entries, whose moments are merged and stored here. Returns those, and the entry after its own."""
    child = slot_child[2 * node + side]
    lower, upper = _entry_box(lower_x, lower_y, lower_z, upper_x, upper_y, upper_z, entry)
    if child >= internal_count:
        centre_radius, normal_area, s0, s1 = _child_moments(child, internal_count, triangles, node_moments)
        return centre_radius, normal_area, s0, s1, lower, upper, entry + 1
    lower_r, upper_r = _entry_box(lower_x, lower_y, lower_z, upper_x, upper_y, upper_z, entry + 1)
    centre_radius_l, normal_l, s0_l, s1_l = _child_moments(slot_child[2 * child], internal_count, triangles,
                                                            node_moments)
    centre_radius_r, normal_r, s0_r, s1_r = _child_moments(slot_child[2 * child + 1], internal_count, triangles,
                                                            node_moments)
    centre_radius, normal_area, s0, s1 = _merged_moments(centre_radius_l, normal_l, s0_l, s1_l, lower, upper,
                                                         centre_radius_r, normal_r, s0_r, s1_r, lower_r, upper_r)
    node_moments[4 * child] = centre_radius
    node_moments[4 * child + 1] = normal_area
    node_moments[4 * child + 2] = s0
    node_moments[4 * child + 3] = s1
    return centre_radius, normal_area, s0, s1, wp.min(lower, lower_r), wp.max(upper, upper_r), entry + 2


@wp.func_native("""
float* values = reinterpret_cast<float*>(&planes.data[0]) + 24 * (entry / 4) + entry % 4;
values[0] = lower[0];
values[4] = lower[1];
values[8] = lower[2];
values[12] = upper[0];
values[16] = upper[1];
values[20] = upper[2];
""")
def _store_entry_box(planes: wp.array(dtype=wp.vec4), entry: int, lower: wp.vec3, upper: wp.vec3):
    """Write a box into entry `entry` (4 k + j) of the planes: six floats, leaving the other entries' alone."""
    ...


@wp.func
def _min4(v: wp.vec4) -> float:
    return wp.min(wp.min(v[0], v[1]), wp.min(v[2], v[3]))


@wp.func
def _max4(v: wp.vec4) -> float:
    return wp.max(wp.max(v[0], v[1]), wp.max(v[2], v[3]))


@wp.kernel(enable_backward=False)
def _refit(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    leaf_face: wp.array(dtype=wp.int32),
    leaf_entry: wp.array(dtype=wp.int32),
    wide_up: wp.array(dtype=wp.int32),
    wide_node: wp.array(dtype=wp.int32),
    wide_child: wp.array(dtype=wp.int32),
    slot_child: wp.array(dtype=wp.int32),
    internal_count: int,
    with_moments: int,
    triangles: wp.array(dtype=wp.vec4),
    planes: wp.array(dtype=wp.vec4),
    arrivals: wp.array(dtype=wp.int32),
    node_moments: wp.array(dtype=wp.vec4),
):
    k = wp.tid()
    tri = faces[leaf_face[k]]
    a = vertices[tri[0]]
    b = vertices[tri[1]]
    c = vertices[tri[2]]
    triangles[3 * k] = wp.vec4(a[0], a[1], a[2], 0.0)
    triangles[3 * k + 1] = wp.vec4(b[0], b[1], b[2], 0.0)
    triangles[3 * k + 2] = wp.vec4(c[0], c[1], c[2], 0.0)
    if internal_count == 0:
        return  # a single triangle, and no tree
    # a leaf's box grows by BOX_SLACK on every side, so its rounded distance from a point stays below the
    # triangle's, and no search prunes a triangle nearer than its bound (see BOX_SLACK)
    lower = wp.min(wp.min(a, b), c) - wp.vec3(_BOX_SLACK)
    upper = wp.max(wp.max(a, b), c) + wp.vec3(_BOX_SLACK)
    # Walk up the 4-wide view; each box goes into its entry of the parent's planes, and the last of a node's entries
    # to arrive merges them: the node's box, and the winding moments (see BvhView.node_moments) of its binary node
    # and of the binary nodes between it and its entries, each from its two children's (Karras 2012, four children
    # at a time). Writers fence before counting their arrival and the merger reads its entries from L2, so no stale
    # value is merged.
    entry = leaf_entry[k]
    while entry >= 0:
        _store_entry_box(planes, entry, lower, upper)
        thread_fence()
        node = entry // 4
        present = int(0)
        for j in range(4):
            if wide_child[4 * node + j] != NO_CHILD:
                present += 1
        if wp.atomic_add(arrivals, node, 1) < present - 1:
            return
        # an absent entry's box is empty (lower above upper), so it drops out of the union
        lower_x = load_coherent_vec4(planes, 6 * node)
        lower_y = load_coherent_vec4(planes, 6 * node + 1)
        lower_z = load_coherent_vec4(planes, 6 * node + 2)
        upper_x = load_coherent_vec4(planes, 6 * node + 3)
        upper_y = load_coherent_vec4(planes, 6 * node + 4)
        upper_z = load_coherent_vec4(planes, 6 * node + 5)
        lower = wp.vec3(_min4(lower_x), _min4(lower_y), _min4(lower_z))
        upper = wp.vec3(_max4(upper_x), _max4(upper_y), _max4(upper_z))
        if with_moments != 0:
            binary = wide_node[node]
            centre_radius_l, normal_l, s0_l, s1_l, lower_l, upper_l, after = _side_moments(
                binary, 0, 0, lower_x, lower_y, lower_z, upper_x, upper_y, upper_z, slot_child, internal_count,
                triangles, node_moments)
            centre_radius_r, normal_r, s0_r, s1_r, lower_r, upper_r, _end = _side_moments(
                binary, 1, after, lower_x, lower_y, lower_z, upper_x, upper_y, upper_z, slot_child, internal_count,
                triangles, node_moments)
            centre_radius, normal_area, s0, s1 = _merged_moments(
                centre_radius_l, normal_l, s0_l, s1_l, lower_l, upper_l,
                centre_radius_r, normal_r, s0_r, s1_r, lower_r, upper_r)
            node_moments[4 * binary] = centre_radius
            node_moments[4 * binary + 1] = normal_area
            node_moments[4 * binary + 2] = s0
            node_moments[4 * binary + 3] = s1
        entry = wide_up[node]
