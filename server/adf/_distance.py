"""Distance queries: one per unique octree corner (the field), and batches of user points (adf or exact).

Every search starts with an upper bound from a face known to be near: for a corner, the face that was
nearest to the same corner last frame (coherence, the paper's section 3.5) or, without one, the face
whose Morton key is nearest the corner's; for an exact point query, the nearest of the faces recorded at
the corners of the point's octree cell. Any face gives a valid bound, so the answer is exact either way;
a tight bound only prunes more of the BVH.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from badf.server.adf._buffers import DeviceBuffers, HostStaged, KeptLaunch, SharedScratch, SideStream
from badf.server.adf._bvh import (
    UNLIMITED_VISITS,
    BvhView,
    cut_bits,
    leaf_distance_held_to_box_sq,
    leaf_distance_sq,
    leaf_triangle,
    nearest_in_entry,
    nearest_leaf_budgeted,
    nearest_leaf_past_ties,
    nearest_leaf_wide,
    spatial_seed,
    winding_number_careful,
)
from badf.server.adf._geometry import (
    atomic_min_packed,
    closest_point_on_triangle,
    feature_on_surface,
    morton3,
    morton3_decode,
    pack_distance_leaf,
    packed_distance_sq,
    packed_leaf,
    quantize,
)
from badf.server.adf._octree import OctreeView, lattice_point, leaf_corner, locate
from badf.server.adf._sign import (
    SIGN_PSEUDONORMAL,
    SIGN_WINDING,
    WOUND_CANCELLED,
    WOUND_INSIDE,
    SignView,
    feature_normal,
    inside_by_pseudonormal,
    inside_by_winding,
    lends_no_normal,
    wound_side,
)
from badf.server.adf._threads import COUNTS_ROOM, MIN_EXACT_CHUNK, launch_per_item, shares_out
from badf.server.adf._tolerances import ORDERED_POINTS, STAGED_POINTS, SURFACE_SNAP

# No fused multiply-adds in this module's kernels (nor in the point queries'): with them, the compiler may
# round the same triangle arithmetic differently where it is inlined at two places, so a seed's distance
# and the walk's, or a whole search's and a subtree search's, could differ in their last bits, and frames
# with and without coherence would not agree bit for bit on CUDA (found on an H100, 2026-11-22: up to 260
# of 12.7K corners of vlasic_samba, by at most 1.2e-7).
EXACT_ROUNDING = {"fuse_fp": False}
wp.set_module_options(EXACT_ROUNDING)

_SURFACE_SNAP = wp.constant(SURFACE_SNAP)
# An ADF gradient shorter than this (a distance field's has length 1) has lost its direction: the point
# is answered exactly instead
_WEAK_GRADIENT = wp.constant(0.01)
# A leaf near the surface whose corners' nearest points lie in directions far apart (inside a sharp edge, in
# a gap between two surfaces: wherever the medial surface crosses it) has a trilinear gradient that can
# point anywhere, away from the surface too. Each corner's direction is the field's gradient there: from its
# nearest point towards it, turned by its sign. A leaf near the surface with two corners whose directions are
# further apart than this cosine (about 78 degrees: right-angle edges, whose two faces' directions are
# exactly 90 degrees apart, come out marked whatever the rounding) is marked (mark_medial_leaves), in bit
# MEDIAL_SHIFT + o of its parent's child mask (o: its octant), above the bits of the children present
_MEDIAL_COSINE = wp.constant(0.2)
MEDIAL_SHIFT = 8
_MEDIAL_SHIFT = wp.constant(MEDIAL_SHIFT)
_OTHER_THAN_MEDIAL = wp.constant(~(255 << MEDIAL_SHIFT))  # the child mask's bits that medial marks keep
# An open mesh's winding number takes every value from 0 to 1 around its rim (each edge that no other face runs
# the other way), so the sheet where its sign jumps off the surface starts at the rim: a leaf the rim crosses
# holds both signs, whatever its corners read (a pocket of the other sign reaching no corner erred by 1.17 cells
# beside a bowl's rim at depth 6). Such a leaf is marked (mark_rim_leaves) in bit RIM_SHIFT + o of its parent's
# child mask, and its points are answered exactly
RIM_SHIFT = 16
_RIM_SHIFT = wp.constant(RIM_SHIFT)
# the rim's edges are cut into pieces no longer than this share of a finest cell: each piece's box, widened by
# _RIM_REACH cells for the rounding of cell coordinates, then meets at most two cells along each axis
_RIM_PIECE = wp.constant(0.5)
_RIM_REACH = wp.constant(1.0e-3)
# How far (in domain sides) off the surface an on-surface exact normal looks for the winding numbers' inside
_SIDE_STEP = wp.constant(16.0 * SURFACE_SNAP)

# Output selection bits of a point query.
OUT_DISTANCE = 1
OUT_CLOSEST = 2
OUT_NORMAL = 4
OUT_FACE = 8
OUTPUT_BITS = {"distance": OUT_DISTANCE, "closest_point": OUT_CLOSEST, "normal": OUT_NORMAL, "face": OUT_FACE}
_OUT_DISTANCE = wp.constant(OUT_DISTANCE)
_OUT_CLOSEST = wp.constant(OUT_CLOSEST)
_OUT_NORMAL = wp.constant(OUT_NORMAL)
_OUT_FACE = wp.constant(OUT_FACE)

_Vec27 = wp.types.vector(length=27, dtype=wp.float32)
# Where a leaf's corners inside and outside add up to more than its diagonal by more than this share of it (for
# the values' rounding), the sign jumps between them (query_points)
_JUMP_SLACK = wp.constant(1.0e-4)

# Threads per block of the corner searches and the corner signs (each thread walks the BVH with a stack
# of its own), and registers per thread. `badf bench engine --kernels --block-sweep --register-sweep` times
# the choices. With the winding numbers running beside the searches, the two kernels share the SMs, and
# what counts is the distance stage. On the bunny at depth 7 (H100, 2026-11-22, two runs at 04:57 and
# 05:12 UTC, after the searches' cheaper triangle test) the stage took:
#   - 1.76 and 1.67 ms at 64 threads per block, against 1.93 and 1.82 at 128 (and 1.81, 1.73 at 32);
#   - 1.70 and 1.57 ms with the searches capped at 64 registers (84 by the compiler's choice: 1.89, 1.82);
#   - 1.73 and 1.63 ms with the signs capped at 48 (they then use 46), against 1.94 and 1.78 at 40.
# Alone (before the second stream) the signs had been fastest at 40 and the searches indifferent to a cap.
# Since the winding walk's budget (2026-12-06) the signs spill more at 48; on an H100 (2026-12-07 03:16, 24 paired
# rounds, docs/results/registers-h100-0313) the bunny's update after the upload took 2.203 ms at 64 against 2.229
# at 56 and 2.240 at 80, and 8398fa0's engine 2.168 at 64 against 2.188 at 48.
SEARCH_BLOCK_DIM = 64
SIGN_BLOCK_DIM = 64
SEARCH_MAX_REGISTERS = 64
SIGN_MAX_REGISTERS = 64
# The point-query kernel's cap (None: the compiler's choice, 255 registers on an H100). At 128 no batch measured was
# slower: 65,536 uniform points with all four outputs, exact in the caller's order, took 3.09 against 4.14 ms on the
# bunny and 1.95 against 2.27 on the armadillo (one H100, 2026-12-07 15:39), 5 to 11% less in Morton order (three
# H100s), ADF up to 13% less; 96 was between them (docs/engine.md, "A batch query's time").
QUERY_MAX_REGISTERS: int | None = 128


class SearchSplit:
    """How corner searches that run long are shared out (see CornerField.compute).

    A corner's search stops after `budget` node visits; the corners that stopped are searched again from
    the bound they reached, by 2^levels threads each, one per subtree of the BVH's cut `levels` deep (rounded up
    to even, as the cut is taken in the 4-wide view: `cut_bits`), `groups` corners at a time. budget 0 searches
    every corner whole in one thread.
    """

    def __init__(self, budget: int, levels: int, groups: int):
        if budget < 0 or (budget > 0 and not (1 <= levels <= 16 and groups >= 1)):
            raise ValueError(f"search split needs budget >= 0 and, with a budget, 1 <= levels <= 16 and groups >= 1;"
                             f" got budget={budget}, levels={levels}, groups={groups}")
        self.budget, self.levels, self.groups = budget, levels, groups

    @staticmethod
    def automatic(device: wp.context.Device, corner_count: int) -> SearchSplit:
        """Split on a GPU that the corners cannot fill, whole searches otherwise.

        A launch of fewer threads than the GPU holds at once lasts as long as its longest searches, and
        splitting those pays: on the bunny (H200, 2026-11-21) the distance stage went from 2.66 to 1.97 ms
        at depth 5 (12.7K corners) and from 2.18 to 2.01 ms at depth 6 (50K). With more corners than that
        the searches are bound by their total work, and splitting gained nothing at depths 7 and 8
        (206K and 833K corners). A CPU launch runs its threads one after another, so splitting only adds
        work there.
        """
        if device.is_cuda and corner_count < device.sm_count * _SPLIT_THREADS_PER_SM:
            return SearchSplit(*_SPLIT)
        return _WHOLE


# (levels, groups) of the far corners' subtree searches, and the far list's size: 1 / FAR_LIST_FRACTION of
# the corners at most (more are searched whole).
_FAR_SPLIT = (6, 4096)
FAR_LIST_FRACTION = 8
FAR_CELLS = 12
_FAR_LIST_FRACTION = wp.constant(FAR_LIST_FRACTION)

# (budget, levels, groups) where splitting pays, and the corner count per SM below which it does.
_SPLIT = (128, 6, 4096)
_SPLIT_THREADS_PER_SM = 1024
_WHOLE = SearchSplit(0, 1, 1)


class CornerField:
    """Signed distance and nearest BVH leaf at each unique corner, and last frame's nearest faces.

    Last frame's corners are kept by lattice key with the domain they were on, so coherence survives the
    domain moving (a corner is matched to the nearest of last frame's lattice points) and the BVH being
    rebuilt (faces, not leaves, are kept).
    """

    # Corners whose starting bound is this many finest cells or more are searched by BVH subtree beside the
    # other corners (list_far_corners); 0: off; None: chosen by far_cells_for.
    far_cells: int | None = None

    def __init__(self, buffers: DeviceBuffers, scratch: SharedScratch):
        """`scratch` is the octree's, which is spent once the corners are listed: the frame's own arrays (the long
        searches' and far corners' lists, the winding numbers' verdicts) are laid over it."""
        self.buffers = buffers
        self.scratch = scratch
        self.device = buffers.device
        self.value: wp.array | None = None
        self.leaf: wp.array | None = None
        self.coherent = False  # whether the last compute started from last frame's faces
        self._previous_count = buffers.ensure("corner.prev_count", 1, wp.int32)
        self._no_previous_frame()
        # last frame's lattice in this frame's local coordinates (origin, 1 / cell), written on the host before
        # each frame (stage_lattice) and read on the device, so a frame captured as a CUDA graph after the domain
        # moved replays for any later move: on CUDA it travels through a pinned buffer, copied within the frame
        self._lattice = HostStaged(buffers.ensure("corner.prev_lattice", 1, wp.vec4))
        self.split: SearchSplit | None = None  # None: SearchSplit.automatic for each compute
        self._last_split = _WHOLE
        self._last_far_cells = 0
        self._beside = SideStream(self.device)  # winding numbers and far corners run on it, beside the searches
        self._choosing = SideStream(self.device)  # and the choice of the frame's sign method (choose_sign) on this

    def compute(self, corner_keys: wp.array, count: wp.array, capacity: int, expected_count: int, bvh: BvhView, cuts,
                sign: SignView, domain, depth: int, band: float | None, *, coherent: bool,
                choose_sign=None) -> None:
        """Distances at the corners (lattice keys, the first count[0] of at most `capacity`) of the domain
        (its world centre and side, and the scale to local coordinates), in local units. The count stays on
        the device; `expected_count` (this frame's or last frame's) only chooses how long searches are shared
        out. `cuts(levels)` gives the BVH's cut that many levels deep (Bvh.cut); `band` is in world units.
        `choose_sign(stream)` queues what decides the frame's sign method on that stream (None: the current
        one); it runs beside the searches, before the signs."""
        b = self.buffers
        split, far_cells = self._shared_out(expected_count, bvh.internal_count, sign.method)
        self._last_split, self._last_far_cells = split, far_cells
        splitting = split.budget > 0
        # the BVH cuts the shared-out searches read, made first: a cut not yet made is launched on the current
        # stream, and the far corners' searches run on a side stream that waits only for what was queued before
        # its fork (a cut made after it was read unwritten on an H200, 2026-11-29)
        far_cut, long_cut = self.make_cuts(split, far_cells, cuts)
        choosing = None
        if choose_sign is not None:
            choosing = self._choosing.fork()
            choose_sign(choosing)
        self.value = b.ensure("corner.value", capacity, wp.float32)
        self.leaf = b.ensure("corner.leaf", capacity, wp.int32)
        use_previous = coherent and self._previous_capacity > 0
        centre, side, origin = domain.centre, domain.local_side, domain.origin
        band = domain.local_band(band)
        cell = side / float(1 << depth)
        if use_previous:
            self._lattice.upload()  # as stage_lattice left it before the frame
        by_winding = sign.method == SIGN_WINDING
        long_corner, long_start, long_best, inside, seeds, far_corner, far_start, far_best = self.scratch.take(
            *self.scratch_layout(capacity, expected_count, bvh.internal_count, sign.method))
        long_count = b.ensure("corner.long_count", 1, wp.int32)
        # the CPU's chunks' counts (launch_per_item); CUDA launches whole
        chunk_counts = b.ensure("corner.chunk_counts", COUNTS_ROOM, wp.int32) if self.device.is_cpu else None
        if splitting:
            long_count.zero_()
        seeding = [corner_keys, count, capacity, origin, cell, 1.0 / side, depth, bvh, band or 0.0,
                   1 if use_previous else 0, self._previous_keys, self._previous_face, self._previous_count,
                   self._previous_capacity, self._lattice.array]
        if far_cells > 0:
            # corners far from the surface, listed with their seeds' bounds and searched by subtree beside the
            # others, from the start of the stage (their single walks would be the launch's longest)
            far_capacity = far_corner.shape[0]
            far_count = b.ensure("corner.far_count", 1, wp.int32)
            far_count.zero_()
            wp.launch(list_far_corners, dim=capacity, inputs=[*seeding, (far_cells * cell) ** 2, far_capacity],
                      outputs=[seeds, self.value, self.leaf, far_count, far_corner, far_start, far_best],
                      device=self.device, block_dim=SEARCH_BLOCK_DIM)
            wp.launch(_settle_far_list, dim=1, inputs=[count, far_capacity], outputs=[far_count], device=self.device)
        beside = self._beside.fork() if by_winding or far_cells > 0 else None
        if far_cells > 0:
            levels, groups = _FAR_SPLIT
            wp.launch(_split_searches, dim=groups << cut_bits(levels),
                      inputs=[corner_keys, origin, cell, bvh, far_cut, cut_bits(levels), groups, far_count,
                              far_capacity, far_corner, far_start],
                      outputs=[far_best], device=self.device, stream=beside)
            wp.launch(_gather_split, dim=groups, inputs=[groups, far_count, far_capacity, far_corner, far_best],
                      outputs=[self.value, self.leaf], device=self.device, stream=beside)
        # shared out over the CPU's cores where each search writes only its own corner's slots (no long list); the
        # per-corner arrays: the keys, the seeds where far corners are listed, the distances and leaves
        launch_per_item(
            corner_searches_budgeted if splitting else corner_searches,
            capacity,
            inputs=[*seeding, split.budget if splitting else UNLIMITED_VISITS, 1 if far_cells > 0 else 0, seeds,
                    far_count if far_cells > 0 else long_count],
            outputs=[self.value, self.leaf, long_count, long_corner, long_start, long_best],
            sliced=None if splitting else (corner_keys, self.value, self.leaf, *((seeds,) if far_cells > 0 else ())),
            counts=chunk_counts,
            device=self.device,
            block_dim=SEARCH_BLOCK_DIM,
        )
        if splitting:
            bits = cut_bits(split.levels)
            wp.launch(_split_searches, dim=split.groups << bits,
                      inputs=[corner_keys, origin, cell, bvh, long_cut, bits, split.groups,
                              long_count, capacity, long_corner, long_start],
                      outputs=[long_best], device=self.device)
            wp.launch(_gather_split, dim=split.groups,
                      inputs=[split.groups, long_count, capacity, long_corner, long_best],
                      outputs=[self.value, self.leaf], device=self.device)
        if by_winding:
            # launched after the searches, so that eagerly (not from a graph) the searches' blocks start first
            launch_per_item(winding_kernel(), capacity, inputs=[corner_keys, count, capacity, origin, cell, bvh],
                            outputs=[inside], sliced=(corner_keys, inside), counts=chunk_counts, device=self.device,
                            block_dim=SIGN_BLOCK_DIM, stream=beside)
        self._beside.join(beside)
        self._choosing.join(choosing)
        launch_per_item(sign_kernel(sign.method), capacity,
                        inputs=[corner_keys, count, capacity, origin, cell, bvh, sign, inside],
                        outputs=[self.value, self.leaf],
                        sliced=(corner_keys, self.value, self.leaf, *((inside,) if by_winding else ())),
                        counts=chunk_counts, device=self.device, block_dim=SIGN_BLOCK_DIM)
        self.coherent = use_previous
        if not coherent:
            self._next = None  # nothing is carried to the next frame
            return
        # this frame's corners (the keys past the count are UNLISTED, after every lattice key, so a binary search
        # over them needs no count), which stay in their buffer until the next frame's octree, and its nearest
        # leaves, whose faces the next frame starts from once this one is kept
        self._next = (corner_keys, count, bvh, capacity, depth, np.asarray(centre, dtype=np.float64).copy(),
                      domain.side)

    def queue_keep(self, report: wp.array, fits_at: int) -> bool:
        """Queue the keeping of the frame just computed (`keep_frame`) at the end of its own work, on the device,
        so that it is part of the frame (and of its graph) rather than launched once the host has its report. It
        takes effect only where report[fits_at] is 1 (the frame fitted its plan). Whether it was queued: not where
        last frame's arrays must be made anew first, as a frame that did not fit would lose them."""
        if self._next is None:
            return False
        capacity = self._next[3]
        if not (self.buffers.holds("corner.prev_keys", capacity) and self.buffers.holds("corner.prev_face", capacity)):
            return False
        self._launch_keep(report, fits_at)
        return True

    def keep_frame(self, report: wp.array, fits_at: int, *, queued: bool) -> None:
        """Make the last computed frame's faces the next frame's starting bounds, once its report has said that it
        fitted (report[fits_at] is 1): launched here unless `queue_keep` `queued` it. A frame that outgrew its
        planned sizes is not kept: the frame run again in its place starts from the same bounds, so its answer
        (down to which of two equally near faces is named) does not depend on the failed run."""
        if self._next is None:
            return
        if not queued:
            capacity = self._next[3]
            self._previous_keys = self.buffers.ensure("corner.prev_keys", capacity, wp.int32)
            self._previous_face = self.buffers.ensure("corner.prev_face", capacity, wp.int32)
            self._launch_keep(report, fits_at)
        _keys, _count, _bvh, capacity, _depth, centre, side = self._next
        self._previous_capacity, self._previous_centre, self._previous_side = capacity, centre, side

    def forget_frame(self) -> None:
        """Drop last frame's nearest faces (trim): the next frame searches from spatial seeds, as a first frame does."""
        wp.synchronize_device(self.device)  # no queued frame still writes them
        self.buffers.release("corner.prev_keys")
        self.buffers.release("corner.prev_face")
        self._no_previous_frame()

    def _no_previous_frame(self) -> None:
        """No frame to start from: one-element stand-ins for last frame's keys and faces, which the kernels take
        and do not read, and no frame computed to keep (its view of the BVH would hold arrays a trim gives back)."""
        self._previous_keys = self.buffers.ensure("corner.prev_keys", 1, wp.int32)
        self._previous_face = self.buffers.ensure("corner.prev_face", 1, wp.int32)
        self._previous_capacity, self._previous_centre, self._previous_side = 0, None, 0.0
        self._next = None

    def _launch_keep(self, report: wp.array, fits_at: int) -> None:
        keys, count, bvh, capacity, depth, _centre, _side = self._next
        # the keys in 32 bits (previous_key): 1 MB less for the bunny than the list's own 64; faces, not leaves,
        # as the BVH is rebuilt when the domain moves: worked out here, from the field's own nearest leaves,
        # rather than kept aside by every frame (1 MB for the bunny)
        wp.launch(_keep_frame, dim=capacity, inputs=[keys, count, depth, self.leaf, capacity, bvh, report, fits_at],
                  outputs=[self._previous_keys, self._previous_face, self._previous_count], device=self.device)

    def scratch_layout(self, capacity: int, expected_count: int, internal_count: int,
                       sign_method: int) -> tuple[tuple[int, type], ...]:
        """The arrays `compute` takes from the scratch for this many corners: the long searches' corners, starts and
        bests (where searches are split), the winding numbers' verdicts (where they sign), the seeds and the far
        corners' list (where far corners are searched by subtree); one element where unused."""
        split, far_cells = self._shared_out(expected_count, internal_count, sign_method)
        far = far_cells > 0
        listed = capacity if split.budget > 0 else 1
        far_listed = max(1, capacity // FAR_LIST_FRACTION) if far else 1
        return ((listed, wp.int32), (listed, wp.int64), (listed, wp.int64),
                (capacity if sign_method == SIGN_WINDING else 1, wp.uint8), (capacity if far else 1, wp.int32),
                (far_listed, wp.int32), (far_listed, wp.int64), (far_listed, wp.int64))

    def _shared_out(self, expected_count: int, internal_count: int, sign_method: int) -> tuple[SearchSplit, int]:
        """How `compute` shares out this many corners' searches: the split of long searches, and the far-corner
        threshold (0 without a tree to cut)."""
        far_cells = self.far_cells_for(sign_method) if internal_count > 0 else 0
        return self.planned_split(expected_count, internal_count), far_cells

    def planned_split(self, expected_count: int, internal_count: int) -> SearchSplit:
        """The split `compute` will use for this many corners (its override, else the automatic choice)."""
        split = self.split or SearchSplit.automatic(self.device, expected_count)
        return split if internal_count > 0 else _WHOLE

    def far_cells_for(self, sign_method: int) -> int:
        """The far-corner threshold `compute` uses with this sign method: far_cells where it is set, else
        FAR_CELLS on CUDA when no winding numbers run beside the searches, else 0.

        The searches leave most SMs idle while their longest walks (corners far from the surface) finish.
        Without winding numbers beside them, searching far corners by subtree from the stage's start shortened
        the distance stage of the armadillo (pseudonormals; H100, 2026-11-22, docs/results/far-*) from
        1.39-1.46 to 1.27-1.34 ms at depth 7 (four runs) and from 2.43-2.50 to 1.93-2.03 ms at depth 8 (three
        runs), at 12 cells. Where winding numbers run beside, they already fill those SMs: the bunny's stage
        was 1.94-2.02 ms at depth 7 and 4.42-4.59 at depth 8 with or without. On the CPU back-end threads run
        one after another, so splitting only adds work. With EXACT_ROUNDING the values do not depend on which
        search found them. After the searches' cheaper triangle test (05:39 and 05:40 runs) the armadillo's
        stage went from 1.53 to 1.37 ms at depth 8 but from 0.96 to 1.00 ms at depth 7: the gain now grows
        with the corner count, which two depths of one mesh are too few to turn into a rule."""
        if self.far_cells is not None:
            return self.far_cells
        if self._beside.enabled and sign_method != SIGN_WINDING:
            return FAR_CELLS
        return 0

    def make_cuts(self, split: SearchSplit, far_cells: int, cuts) -> tuple:
        """The BVH cuts that `compute` reads with this split and far-corner threshold, made now by `cuts(levels)`
        (Bvh.cut): the far corners' and the long searches' (None: that cut is not read)."""
        return (cuts(_FAR_SPLIT[0]) if far_cells > 0 else None, cuts(split.levels) if split.budget > 0 else None)

    def coherence_key(self) -> tuple:
        """What `compute` takes by value from last frame (for reusing a captured frame): where last frame's
        lattice lies is read on the device (stage_lattice)."""
        return (self._previous_capacity,)

    def stage_lattice(self, domain, depth: int) -> None:
        """Write where last frame's lattice lies in this frame's local coordinates (its domain may have moved),
        for the next `compute` or a replay of one; call before each frame."""
        if self._previous_centre is None:
            return
        scale = domain.scale
        origin = (self._previous_centre - domain.centre) * scale - self._previous_side * scale / 2.0
        inv_cell = float(1 << depth) / (self._previous_side * scale)
        self._lattice.host()[0] = np.array([*origin, inv_cell], dtype=np.float32)

    @property
    def search_budget(self) -> int:
        """The last compute's visit budget per corner search, 0 where every search ran whole."""
        return self._last_split.budget

    def far_corners(self) -> int:
        """How many corners the last compute found far (-1: too many, so all were searched whole; a device
        read, for tools)."""
        if self._last_far_cells <= 0:
            return 0
        return int(self.buffers.ensure("corner.far_count", 1, wp.int32).numpy()[0])

    def long_searches(self) -> int:
        """How many corners of the last compute ran past the search budget (a device read, for tools)."""
        if self._last_split.budget <= 0:
            return 0
        return int(self.buffers.ensure("corner.long_count", 1, wp.int32).numpy()[0])


class PointQuery:
    """Device buffers for batches of query points, reused from batch to batch, and on CUDA pinned host twins of
    them for batches of at most STAGED_POINTS."""

    def __init__(self, buffers: DeviceBuffers):
        self.buffers = buffers
        self.device = buffers.device
        self.staging = self.device.is_cuda  # (tests turn it on for the CPU, where the twins are plain host arrays)
        self._staged: dict[str, wp.array] = {}
        # batches of at least `ordered_from` points, in these modes, are walked in their points' Morton order
        # (`_order`): exact ones, whose walks are long. ADF ones never won back the sort (about 0.1 ms at 65,536
        # points on an H100; bench/probes/probe_query_order.py, docs/engine.md "A batch query's time")
        self.ordered_modes: set[str] = {"exact"}
        self.ordered_from = ORDERED_POINTS["cuda" if self.device.is_cuda else "cpu"]
        # a batch's launch, replayed for the next batch with the same arguments (small queries in a loop), and the
        # points' placing, kept as the same objects while their values hold so that the launch can be replayed
        self._launch = KeptLaunch()
        self._placing: tuple[tuple, list] | None = None

    def _stage(self, name: str, count: int, dtype) -> wp.array | None:
        """A pinned host array of at least `count` elements for a batch on CUDA of at most STAGED_POINTS, grown
        with headroom; None on the CPU and for larger batches. Reused by the next batch, which starts once this
        one's copies are done (`run` waits for the device)."""
        if not self.staging or count > STAGED_POINTS:
            return None
        arr = self._staged.get(name)
        if arr is None or arr.shape[0] < count:
            size = count if arr is None else min(STAGED_POINTS, max(count, int(arr.shape[0] * 1.5)))
            arr = wp.empty(size, dtype=dtype, device="cpu", pinned=self.device.is_cuda)
            self._staged[name] = arr
        return arr

    def give_back(self) -> None:
        """Free the pinned host buffers and let go of the kept launch's arrays (a trim); the next batch makes them
        again."""
        self._staged.clear()
        self._launch.clear()

    def let_go_unless(self, arguments: tuple) -> None:
        """Let go of the kept launch's arguments unless it takes each of these (a frame's views and corner arrays):
        an array a frame replaced is then freed at once, and a frame that replaced none keeps the launch."""
        self._launch.let_go_unless(arguments)

    def _placed(self, offset: np.ndarray, scale: float, turn: np.ndarray | None, shift: np.ndarray | None) -> list:
        """The query kernel's placing arguments (offset, to_local, turned, turn, shift): the last batch's objects
        where the values are the same."""
        key = (offset.tobytes(), float(scale), None if turn is None else turn.tobytes(),
               None if shift is None else shift.tobytes())
        if self._placing is None or self._placing[0] != key:
            placing = [wp.vec3(*offset), float(scale), 0 if turn is None else 1,
                       wp.mat33(*(np.eye(3) if turn is None else turn).reshape(-1)),
                       wp.vec3(*(np.zeros(3) if shift is None else shift))]
            self._placing = (key, placing)
        return self._placing[1]

    def _order(self, points: wp.array, n: int, placing: list, octree: OctreeView, side: float,
               exact: bool) -> wp.array | None:
        """The batch's point indices sorted by their Morton keys in the domain (10 bits an axis, clamped to it), for
        a batch to be walked in that order; None where it is walked as it came. A caller's points come in its own
        order (uniform samples, another mesh's vertices): a warp of 32 scattered points waits for the longest of 32
        unrelated walks, where 32 neighbours walk much the same nodes. Each thread still answers its own point, so
        every answer is the same either way."""
        if ("exact" if exact else "adf") not in self.ordered_modes or n < self.ordered_from:
            return None
        keys = self.buffers.ensure("query.order_keys", 2 * n, wp.int32, headroom=True)  # twice: the radix sort's room
        order = self.buffers.ensure("query.order", 2 * n, wp.int32, headroom=True)
        wp.launch(_point_keys, dim=n, inputs=[points, *placing, octree.origin, 1.0 / side], outputs=[keys, order],
                  device=self.device)
        wp.utils.radix_sort_pairs(keys, order, n, end_bit=3 * _ORDER_BITS)
        return order

    def run(self, points: np.ndarray, offset: np.ndarray, scale: float, *, exact: bool, outputs: int,
            octree: OctreeView, corner_value: wp.array, corner_leaf: wp.array, bvh: BvhView, sign: SignView,
            side: float, band: float | None, results: dict[str, np.ndarray], start: int,
            turn: np.ndarray | None = None, shift: np.ndarray | None = None) -> None:
        """Answer one batch of float32 points, `(points - offset) * scale` in the engine's local coordinates, or
        `turn @ ((points - offset) * scale) - shift` where a turn is given (side and band in local units too); copy
        the asked outputs, in local units, into results[...][start:]."""
        b = self.buffers
        n = len(points)
        distance = b.ensure("query.distance", n if outputs & OUT_DISTANCE else 1, wp.float32, headroom=True)
        closest = b.ensure("query.closest", n if outputs & OUT_CLOSEST else 1, wp.vec3, headroom=True)
        normal = b.ensure("query.normal", n if outputs & OUT_NORMAL else 1, wp.vec3, headroom=True)
        face = b.ensure("query.face", n if outputs & OUT_FACE else 1, wp.int32, headroom=True)
        device_points = b.ensure("query.points", n, wp.vec3, headroom=True)
        stage = self._stage("points", n, wp.vec3)
        # float64 points are rounded to float32 in these writes, as Warp's own conversion does
        if stage is not None:
            stage.numpy()[:n] = points
            wp.copy(device_points, stage, count=n)
        elif self.device.is_cpu:  # written where the kernel reads them
            device_points.numpy()[:n] = points
        else:
            wp.copy(device_points, wp.array(points, dtype=wp.vec3, device="cpu", copy=False), count=n)
        placing = self._placed(offset, scale, turn, shift)
        order = self._order(device_points, n, placing, octree, side, exact)
        kernel = query_kernel(sign.method)
        inputs = [device_points, order, 0 if order is None else 1, *placing, 1 if exact else 0, outputs, octree,
                  corner_value, corner_leaf, bvh, sign, 1.0 / side, band or 0.0]
        # exact points walk the BVH each, so on the CPU smaller batches of them are shared out over the cores
        min_chunk = MIN_EXACT_CHUNK if exact else None
        if not shares_out(self.device, n, min_chunk=min_chunk):
            self._launch.launch(kernel, n, inputs, [distance, closest, normal, face], self.device)
        else:
            # shared out over the CPU's cores by points: the points and the outputs asked for (the others hold one
            # slot); in order, a thread reads its point and writes its outputs where the order says: only the order
            # is cut
            asked = [arr for arr, bit in ((distance, OUT_DISTANCE), (closest, OUT_CLOSEST), (normal, OUT_NORMAL),
                                          (face, OUT_FACE)) if outputs & bit]
            launch_per_item(kernel, n, inputs=inputs, outputs=[distance, closest, normal, face],
                            sliced=(device_points, *asked) if order is None else (order,), min_chunk=min_chunk,
                            device=self.device)
        staged = []
        for name, bit, arr, dtype in (
            ("distance", OUT_DISTANCE, distance, wp.float32),
            ("closest_point", OUT_CLOSEST, closest, wp.vec3),
            ("normal", OUT_NORMAL, normal, wp.vec3),
            ("face", OUT_FACE, face, wp.int32),
        ):
            if outputs & bit:
                host = self._stage(name, n, dtype)
                if host is None and self.device.is_cpu:  # read where the kernel wrote them
                    results[name][start : start + n] = arr.numpy()[:n]
                    continue
                if host is None:
                    host = wp.array(results[name][start : start + n], dtype=dtype, device="cpu", copy=False)
                else:
                    staged.append((name, host))
                wp.copy(host, arr, count=n)
        wp.synchronize_device(self.device)
        for name, host in staged:
            results[name][start : start + n] = host.numpy()[:n]


# bits an axis of the Morton keys that order a batch of query points: 2^10 cells a side, 30-bit keys
_ORDER_BITS = 10


@wp.func
def _placed_point(point: wp.vec3, offset: wp.vec3, to_local: float, turned: int, turn: wp.mat33, shift: wp.vec3):
    """A query point in the engine's local coordinates: `(point - offset) * to_local`, turned into the field's frame
    where a rigid frame's turn is given (DistanceField._answer)."""
    p = (point - offset) * to_local
    if turned != 0:
        p = turn * p - shift
    return p


@wp.kernel(enable_backward=False)
def _point_keys(points: wp.array(dtype=wp.vec3), offset: wp.vec3, to_local: float, turned: int, turn: wp.mat33,
                shift: wp.vec3, origin: wp.vec3, inv_side: float, keys: wp.array(dtype=wp.int32),
                order: wp.array(dtype=wp.int32)):
    """Each point's Morton key in the domain's cube (clamped to it), placed as the query kernel places it, and its
    index, for the sort that orders a batch."""
    i = wp.tid()
    p = _placed_point(points[i], offset, to_local, turned, turn, shift)
    cell = quantize(p, origin, inv_side * float(1 << _ORDER_BITS), 1 << _ORDER_BITS)
    keys[i] = wp.int32(morton3(cell[0], cell[1], cell[2]))
    order[i] = i


@wp.func
def _held_to_band(seed: int, seed_sq: float, band: float):
    """A search's start from its seed leaf at squared distance seed_sq: (seed, seed_sq), or (-1, band^2)
    where the seed lies beyond `band` (> 0)."""
    if band > 0.0 and band * band < seed_sq:
        return -1, band * band
    return seed, seed_sq


@wp.func
def _seed_bound(bvh: BvhView, p: wp.vec3, seed: int, band: float):
    """A corner search's start from its seed leaf (see _held_to_band)."""
    return _held_to_band(seed, leaf_distance_sq(bvh, seed, p), band)


def _banded_search(nearest_leaf, leaf_distance_sq):
    """`nearest_leaf` (one of the BVH's two searches, which values a leaf by `leaf_distance_sq`) started from a
    seed leaf and held to a band."""

    def nearest_with_band(bvh: BvhView, p: wp.vec3, seed: int, band: float, budget: int):
        """Nearest leaf from a seed leaf in at most `budget` node visits: (leaf, squared distance, finished);
        leaf -1 when nothing lies within `band` (> 0). An unfinished search's answer is an upper bound."""
        best, best_sq = _held_to_band(seed, leaf_distance_sq(bvh, seed, p), band)
        best, best_sq, finished = nearest_leaf(bvh, p, best, best_sq, budget)
        return best, best_sq, finished

    return wp.func(nearest_with_band, module="unique")


# the corner searches' and the queries' (which pass over tied boxes: see `_wide_searches`), both over the 4-wide view
_nearest_with_band = _banded_search(nearest_leaf_wide, leaf_distance_sq)
_nearest_with_band_budgeted = _banded_search(nearest_leaf_budgeted, leaf_distance_sq)
_nearest_past_ties = _banded_search(nearest_leaf_past_ties, leaf_distance_held_to_box_sq)


@wp.func
def _corner_seed(bvh: BvhView, p: wp.vec3, origin: wp.vec3, inv_side: float, depth: int, coherent: int,
                 previous_keys: wp.array(dtype=wp.int32), previous_face: wp.array(dtype=wp.int32),
                 previous_count: wp.array(dtype=wp.int32), previous_capacity: int,
                 previous_lattice: wp.array(dtype=wp.vec4)) -> int:
    """A corner's seed leaf: by last frame's nearest face (coherent), else by Morton key."""
    if coherent != 0:
        return coherent_seed(bvh, p, depth, previous_keys, previous_face, previous_count, previous_capacity,
                             previous_lattice)
    return spatial_seed(bvh, p, origin, inv_side)


@wp.func
def previous_key(key: wp.int64, depth: int) -> wp.int32:
    """A lattice key as last frame's corners keep it, in 32 bits: the key itself up to depth 9 (3 (depth + 1) bits),
    and at depth 10 without its lowest 2 bits, so that it names a block of four lattice points. Order is kept, so
    the keys stay sorted; a seed found through a block is a neighbour's face, which bounds a search as well as any
    (the search's answer does not depend on its start)."""
    return wp.int32(key >> wp.int64(wp.max(0, 3 * (depth + 1) - 31)))


@wp.kernel(enable_backward=False)
def _keep_frame(keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), depth: int,
                leaf: wp.array(dtype=wp.int32), capacity: int, bvh: BvhView, report: wp.array(dtype=wp.int32),
                fits_at: int, kept: wp.array(dtype=wp.int32), face: wp.array(dtype=wp.int32),
                kept_count: wp.array(dtype=wp.int32)):
    """Where the frame fitted (report[fits_at] == 1): every listed key as `previous_key` (past the count, as past
    the list, a key after every lattice key), the face of each corner's nearest leaf, and the count."""
    i = wp.tid()
    if report[fits_at] != 1:
        return
    n = count[0]
    if i == 0:
        kept_count[0] = n
    if i < n:
        kept[i] = previous_key(keys[i], depth)
        face[i] = bvh.leaf_face[leaf[i]]
    else:
        kept[i] = wp.int32(2147483647)


@wp.func
def _search_sorted(keys: wp.array(dtype=wp.int32), count: int, key: wp.int32) -> int:
    lo = int(0)
    hi = count
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


_KERNELS: dict[tuple[str, int], wp.Kernel] = {}


def sign_kernel(method: int) -> wp.Kernel:
    """The corner-sign kernel compiled for one sign method, so the other methods' code costs it no registers."""
    key = ("sign", method)
    if key not in _KERNELS:
        _KERNELS[key] = _make_sign_kernel(method)
    return _KERNELS[key]


def query_kernel(method: int) -> wp.Kernel:
    """The point-query kernel compiled for one sign method."""
    key = ("query", method)
    if key not in _KERNELS:
        _KERNELS[key] = _make_query_kernel(method)
    return _KERNELS[key]


@wp.func
def _face_normal(bvh: BvhView, leaf: int) -> wp.vec3:
    """The unit normal of a leaf's face, or zero where the face is degenerate (DEGENERATE_AREA)."""
    a, b, c = leaf_triangle(bvh, leaf)
    n = wp.cross(b - a, c - a)
    length = wp.length(n)
    if lends_no_normal(a, b, c, length):
        return wp.vec3(0.0)
    return n / length


@wp.func
def _surface_normal(tree: OctreeView, corner_leaf: wp.array(dtype=wp.int32), node: int, octant: int, bvh: BvhView,
                    p: wp.vec3, leaf: int):
    """(unit normal, the leaf it is of) at a point on `leaf`'s face: that face's normal or, where the face has
    none (it is degenerate: a sliver along another face's edge, say), the normal of the face nearest p among
    those recorded at the corners of p's octree leaf (node, octant). Where none has one (a stray segment):
    the direction from the face to p, or any direction across the face's longest edge."""
    n = _face_normal(bvh, leaf)
    if wp.length_sq(n) > 0.0:
        return n, leaf
    used = leaf
    best_sq = float(3.0e38)
    for corner in range(8):
        other = corner_leaf[leaf_corner(tree, node, octant, corner)]
        m = _face_normal(bvh, other)
        if wp.length_sq(m) > 0.0:
            d_sq = leaf_distance_sq(bvh, other, p)
            if d_sq < best_sq:
                best_sq = d_sq
                n = m
                used = other
    if wp.length_sq(n) > 0.0:
        return n, used
    a, b, c = leaf_triangle(bvh, leaf)
    foot, _feature = closest_point_on_triangle(p, a, b, c)
    if wp.length_sq(p - foot) > 0.0:
        return wp.normalize(p - foot), leaf
    edge = b - a
    if wp.length_sq(c - a) > wp.length_sq(edge):
        edge = c - a
    across = wp.cross(edge, wp.vec3(1.0, 0.0, 0.0))
    if wp.length_sq(across) <= 1.0e-6 * wp.length_sq(edge):
        across = wp.cross(edge, wp.vec3(0.0, 1.0, 0.0))
    if wp.length_sq(across) > 0.0:
        return wp.normalize(across), leaf
    return wp.vec3(0.0, 0.0, 1.0), leaf  # a face that is a point


@wp.func
def _nearest_corner_face(tree: OctreeView, corner_leaf: wp.array(dtype=wp.int32), node: int, octant: int,
                         bvh: BvhView, p: wp.vec3) -> int:
    """The leaf nearest p of those recorded at the corners of p's octree leaf (node, octant); the first of
    equals in corner order."""
    best = corner_leaf[leaf_corner(tree, node, octant, 0)]
    best_sq = leaf_distance_sq(bvh, best, p)
    for corner in range(1, 8):
        leaf = corner_leaf[leaf_corner(tree, node, octant, corner)]
        d_sq = leaf_distance_sq(bvh, leaf, p)
        if d_sq < best_sq:
            best_sq = d_sq
            best = leaf
    return best


@wp.func
def _corner_direction(bvh: BvhView, leaf: int, value: float, q: wp.vec3, inv_side: float) -> wp.vec3:
    """The field's unit gradient at lattice point q, whose nearest face is sorted leaf `leaf` and whose value
    is `value`: from q's nearest point towards q, turned inward where the value is negative; zero where there
    is none (no face within the band, q on the surface)."""
    if leaf < 0:
        return wp.vec3(0.0)
    a, b, c = leaf_triangle(bvh, leaf)
    foot, _feature = closest_point_on_triangle(q, a, b, c)
    away = q - foot
    length = wp.length(away)
    if length * inv_side <= _SURFACE_SNAP:
        return wp.vec3(0.0)
    return wp.where(value < 0.0, -1.0, 1.0) * away / length


@wp.kernel(enable_backward=False)
def mark_medial_leaves(
    node_keys: wp.array(dtype=wp.int64),
    totals: wp.array(dtype=wp.int32),
    internal_capacity: int,
    tree: OctreeView,
    corner_value: wp.array(dtype=wp.float32),
    corner_leaf: wp.array(dtype=wp.int32),
    bvh: BvhView,
    inv_side: float,
    has_sign: int,
    child_mask: wp.array(dtype=wp.int32),
):
    """Mark each child of an internal node that has a corner near the surface (nearer for a field that
    `has_sign`) and two corners whose directions (_corner_direction) are further apart than _MEDIAL_COSINE,
    in the node's child mask (bit _MEDIAL_SHIFT + octant; a child that is itself a node is marked too, and
    never read). One thread per internal node; its 27 lattice points' directions are worked out once each."""
    node = wp.tid()
    if node >= wp.min(totals[1], internal_capacity):
        return
    key = node_keys[node]
    level = int(key >> wp.int64(32))
    parent = morton3_decode(key & wp.int64(0xFFFFFFFF))
    child = tree.cell * float(1 << (tree.depth - level - 1))  # a child's side
    base = tree.origin + 2.0 * child * wp.vec3(float(parent[0]), float(parent[1]), float(parent[2]))
    ux = _Vec27()
    uy = _Vec27()
    uz = _Vec27()
    reach = _Vec27()  # |value|
    for point in range(27):
        slot = tree.corner_slot[node * 27 + point]
        q = base + child * wp.vec3(float(point // 9), float((point // 3) % 3), float(point % 3))
        u = _corner_direction(bvh, corner_leaf[slot], corner_value[slot], q, inv_side)
        ux[point] = u[0]
        uy[point] = u[1]
        uz[point] = u[2]
        reach[point] = wp.abs(corner_value[slot])
    # near the surface: a corner within the child's diagonal of it (else the surface does not cross it) and,
    # signed, within a finest diagonal (a contact's reach). Signed coarse leaves farther out keep the
    # gradient: the medial surface runs through most of them inside a solid, and exact normals there, with
    # their winding numbers, cost about as much as exact mode (within two finest diagonals, 8% of the points
    # spread over the bunny's box went exact on the CPU, and normal queries there took 2.57 ms on the H100 against
    # 0.82 to 0.98 before any marking, 2026-11-22 23:44)
    near = 1.7320508 * child
    if has_sign != 0:
        near = 1.7320508 * wp.min(child, tree.cell)
    marks = int(0)
    for octant in range(8):
        nearest = float(3.0e38)
        least = float(1.0)
        for corner in range(8):
            i = lattice_point(octant, corner)
            nearest = wp.min(nearest, reach[i])
            ui = wp.vec3(ux[i], uy[i], uz[i])
            for other in range(corner):
                j = lattice_point(octant, other)
                uj = wp.vec3(ux[j], uy[j], uz[j])
                if wp.length_sq(ui) > 0.0 and wp.length_sq(uj) > 0.0:  # a corner on the surface has no direction
                    least = wp.min(least, wp.dot(ui, uj))
        if nearest <= near and least < _MEDIAL_COSINE:
            marks |= 1 << octant
    child_mask[node] = (child_mask[node] & _OTHER_THAN_MEDIAL) | (marks << _MEDIAL_SHIFT)


@wp.kernel(enable_backward=False)
def mark_rim_leaves(
    vertices: wp.array(dtype=wp.vec3),
    rim_edges: wp.array(dtype=wp.vec2i),
    tree: OctreeView,
    child_mask: wp.array(dtype=wp.int32),
):
    """Mark every leaf that rim edge e (vertex ids) crosses, in its parent's child mask (bit _RIM_SHIFT + octant):
    the edge is cut into pieces of at most _RIM_PIECE finest cells, and each leaf holding a finest cell that a
    piece's box (widened by _RIM_REACH cells) meets is marked, a few beside the edge with them. One thread per edge;
    an edge as long as the domain's diagonal at depth 10 is about 3,600 pieces."""
    e = wp.tid()
    edge = rim_edges[e]
    a = vertices[edge[0]]
    b = vertices[edge[1]]
    inv_cell = 1.0 / tree.cell
    resolution = 1 << tree.depth
    reach = wp.vec3(_RIM_REACH * tree.cell)
    pieces = int(wp.ceil(wp.min(wp.length(b - a) * inv_cell, 4.0 * float(resolution)) / _RIM_PIECE)) + 1
    for k in range(pieces):
        p = a + (b - a) * (float(k) / float(pieces))
        q = a + (b - a) * (float(k + 1) / float(pieces))
        # the cells a query's own quantisation puts the piece's box corners in
        low = quantize(wp.min(p, q) - reach, tree.origin, inv_cell, resolution)
        high = quantize(wp.max(p, q) + reach, tree.origin, inv_cell, resolution)
        for x in range(low[0], high[0] + 1):
            for y in range(low[1], high[1] + 1):
                for z in range(low[2], high[2] + 1):
                    node, octant, _level = locate(tree, wp.vec3i(x, y, z))
                    wp.atomic_or(child_mask, node, 1 << (_RIM_SHIFT + octant))


@wp.func
def _nearest_point_from_corners(tree: OctreeView, corner_leaf: wp.array(dtype=wp.int32), node: int, octant: int,
                                bvh: BvhView, p: wp.vec3):
    """(p's nearest leaf, p's closest point on it, its feature), searched from the nearest of the faces recorded
    at the corners of p's octree leaf (node, octant); p's own face need not be one of them."""
    seed = _nearest_corner_face(tree, corner_leaf, node, octant, bvh, p)
    leaf, _best_sq, _done = _nearest_past_ties(bvh, p, seed, 0.0, UNLIMITED_VISITS)
    a, b, c = leaf_triangle(bvh, leaf)
    foot, feature = closest_point_on_triangle(p, a, b, c)
    return leaf, foot, feature


@wp.func
def _winds_inward(bvh: BvhView, leaf: int, inv_side: float) -> bool:
    """Whether `leaf`'s face winds inwards by the winding numbers: |w| is larger a step along its normal
    from its centroid than a step against it. Looked at from the centroid, not from a point on the face's
    edge, where a step along its normal can land in the plane of the next face and |w| there is rounding."""
    a, b, c = leaf_triangle(bvh, leaf)
    n = wp.cross(b - a, c - a)
    length = wp.length(n)
    if length == 0.0:
        return False
    centre = (a + b + c) / 3.0
    step = n * (_SIDE_STEP / (inv_side * length))
    ahead, _cancelled_ahead = winding_number_careful(bvh, centre + step)
    behind, _cancelled_behind = winding_number_careful(bvh, centre - step)
    return wp.abs(ahead) > wp.abs(behind)


@wp.func
def _lattice_point(key: wp.int64, origin: wp.vec3, cell: float) -> wp.vec3:
    lattice = morton3_decode(key)
    return origin + wp.vec3(float(lattice[0]), float(lattice[1]), float(lattice[2])) * cell


@wp.func
def coherent_seed(bvh: BvhView, p: wp.vec3, depth: int, previous_keys: wp.array(dtype=wp.int32),
                  previous_face: wp.array(dtype=wp.int32), previous_count: wp.array(dtype=wp.int32),
                  previous_capacity: int, previous_lattice: wp.array(dtype=wp.vec4)) -> int:
    """The leaf of the face nearest last frame's nearest lattice point to p (the same point while the
    domain stays), or its neighbour in Morton order: that face bounds p's search either way."""
    lattice = previous_lattice[0]  # origin, 1 / cell (CornerField.stage_lattice)
    q = (p - wp.vec3(lattice[0], lattice[1], lattice[2])) * lattice[3]
    top = 1 << depth
    key = morton3(
        wp.clamp(int(wp.round(q[0])), 0, top),
        wp.clamp(int(wp.round(q[1])), 0, top),
        wp.clamp(int(wp.round(q[2])), 0, top),
    )
    listed = wp.min(previous_count[0], previous_capacity)
    slot = wp.min(_search_sorted(previous_keys, listed, previous_key(key, depth)), listed - 1)
    return bvh.face_leaf[previous_face[slot]]


@wp.func
def list_long_search(corner: int, best_sq: float, best_leaf: int, listed: int, long_count: wp.array(dtype=wp.int32),
                     long_corner: wp.array(dtype=wp.int32), long_start: wp.array(dtype=wp.int64),
                     long_best: wp.array(dtype=wp.int64)) -> bool:
    """A search too long for one thread, for _split_searches to take on from the (bound, leaf) it reached;
    whether it fitted the list's `listed` entries (the count goes on past them)."""
    item = wp.atomic_add(long_count, 0, 1)
    if item >= listed:
        return False
    long_corner[item] = corner
    start = pack_distance_leaf(best_sq, best_leaf)
    long_start[item] = start
    long_best[item] = start
    return True


@wp.func
def _write_answer(i: int, best: int, best_sq: float, seed: int, band: float, distance: wp.array(dtype=wp.float32),
                  nearest: wp.array(dtype=wp.int32)):
    """A corner's unsigned distance and nearest leaf, or (band, -1 - seed) where nothing lay within the band
    (the sign kernel turns the seed back into its leaf)."""
    if best >= 0:
        distance[i] = wp.sqrt(best_sq)
        nearest[i] = best
    else:
        distance[i] = band
        nearest[i] = -1 - seed


def _corner_searches(budgeted: bool) -> wp.Kernel:
    """The corner searches' kernel: every walk run to its end, or (`budgeted`) walks cut at `budget` node visits
    and listed as long, for the subtree searches that finish them (`SearchSplit`)."""
    nearest_with_band = _nearest_with_band_budgeted if budgeted else _nearest_with_band

    def corner_searches(
        corner_keys: wp.array(dtype=wp.int64),
        count: wp.array(dtype=wp.int32),
        capacity: int,
        origin: wp.vec3,
        cell: float,
        inv_side: float,
        depth: int,
        bvh: BvhView,
        band: float,
        coherent: int,
        previous_keys: wp.array(dtype=wp.int32),
        previous_face: wp.array(dtype=wp.int32),
        previous_count: wp.array(dtype=wp.int32),
        previous_capacity: int,
        previous_lattice: wp.array(dtype=wp.vec4),
        budget: int,
        seeded: int,
        seeds: wp.array(dtype=wp.int32),
        seeded_far_count: wp.array(dtype=wp.int32),
        distance: wp.array(dtype=wp.float32),
        nearest: wp.array(dtype=wp.int32),
        long_count: wp.array(dtype=wp.int32),
        long_corner: wp.array(dtype=wp.int32),
        long_start: wp.array(dtype=wp.int64),
        long_best: wp.array(dtype=wp.int64),
    ):
        """Unsigned distance and nearest leaf of each corner; -1 - seed where nothing lies within the band.
        Where `budgeted`, a search that needs more than `budget` node visits is listed as long, with the bound it
        reached; otherwise `budget` and the long list are not read.
        With `seeded`, each corner's seed leaf comes from `seeds` (list_far_corners), and a corner whose seed
        is negative was found far and is searched by subtree, unless the far list was dropped.

        The sign is a separate kernel (sign_kernel), so this one carries neither the winding number's stack
        nor its registers. A combined kernel proved fragile: with an experiment's extra code in the search it
        ran 4x slower on an H200 (2026-11-21). Apart, with the triangle box test, the bunny's corner stage
        took 3.13 ms there, against 3.35 ms for the combined kernel earlier that day.
        """
        i = wp.tid()
        if i >= wp.min(count[0], capacity):
            return
        p = _lattice_point(corner_keys[i], origin, cell)
        seed = int(-1)
        if seeded != 0:
            seed = seeds[i]
            if seed < 0:
                if seeded_far_count[0] >= 0:
                    return  # a far corner, searched by subtree
                seed = -2 - seed
        else:
            seed = _corner_seed(bvh, p, origin, inv_side, depth, coherent, previous_keys, previous_face, previous_count,
                                previous_capacity, previous_lattice)
        best_leaf, best_sq, finished = nearest_with_band(bvh, p, seed, band, budget)
        _write_answer(i, best_leaf, best_sq, seed, band, distance, nearest)
        if wp.static(budgeted):
            if not finished:
                list_long_search(i, best_sq, best_leaf, capacity, long_count, long_corner, long_start, long_best)

    corner_searches.__name__ = corner_searches.__qualname__ = "corner_searches" + ("_budgeted" if budgeted else "")
    return wp.kernel(corner_searches, enable_backward=False, module="unique", cuda_max_registers=SEARCH_MAX_REGISTERS,
                     module_options=EXACT_ROUNDING)


corner_searches = _corner_searches(budgeted=False)
corner_searches_budgeted = _corner_searches(budgeted=True)


@wp.kernel(enable_backward=False)
def list_far_corners(
    corner_keys: wp.array(dtype=wp.int64),
    count: wp.array(dtype=wp.int32),
    capacity: int,
    origin: wp.vec3,
    cell: float,
    inv_side: float,
    depth: int,
    bvh: BvhView,
    band: float,
    coherent: int,
    previous_keys: wp.array(dtype=wp.int32),
    previous_face: wp.array(dtype=wp.int32),
    previous_count: wp.array(dtype=wp.int32),
    previous_capacity: int,
    previous_lattice: wp.array(dtype=wp.vec4),
    far_sq: float,
    far_capacity: int,
    seeds: wp.array(dtype=wp.int32),
    distance: wp.array(dtype=wp.float32),
    nearest: wp.array(dtype=wp.int32),
    far_count: wp.array(dtype=wp.int32),
    far_corner: wp.array(dtype=wp.int32),
    far_start: wp.array(dtype=wp.int64),
    far_best: wp.array(dtype=wp.int64),
):
    """Each corner's seed leaf; a corner whose starting bound (its seed's distance, or the band) is at least
    sqrt(far_sq) is listed for _split_searches with that bound, its seed's answer written as a start, and
    its seed stored as -2 - seed so corner_searches leaves it. Such corners are few and their walks the
    longest."""
    i = wp.tid()
    if i >= wp.min(count[0], capacity):
        return
    p = _lattice_point(corner_keys[i], origin, cell)
    seed = _corner_seed(bvh, p, origin, inv_side, depth, coherent, previous_keys, previous_face, previous_count,
                        previous_capacity, previous_lattice)
    seeds[i] = seed
    best, best_sq = _seed_bound(bvh, p, seed, band)
    if best_sq < far_sq:
        return
    seeds[i] = -2 - seed  # far: corner_searches leaves it unless _settle_far_list drops the list
    if list_long_search(i, best_sq, best, far_capacity, far_count, far_corner, far_start, far_best):
        _write_answer(i, best, best_sq, seed, band, distance, nearest)  # the start, which the split improves on


@wp.kernel(enable_backward=False)
def _settle_far_list(count: wp.array(dtype=wp.int32), far_capacity: int, far_count: wp.array(dtype=wp.int32)):
    """More far corners than 1 / FAR_LIST_FRACTION of the corners (after a domain move, most seeds are
    poor), or than the list holds: the list is dropped (count -1) and corner_searches searches them all whole.
    Which corners take which path then depends on the frame alone, not on the order the listing threads ran
    in. The list holds 1 / FAR_LIST_FRACTION of the planned corners, fewer than that of a frame that outgrew its
    plan; a far corner left off it and not searched whole would keep a stale nearest leaf, which the sign kernel
    reads a triangle by (an illegal address on an H200, 2026-11-29)."""
    if far_count[0] > wp.min(count[0] // _FAR_LIST_FRACTION, far_capacity):
        far_count[0] = -1


@wp.kernel(enable_backward=False)
def _split_searches(
    corner_keys: wp.array(dtype=wp.int64),
    origin: wp.vec3,
    cell: float,
    bvh: BvhView,
    cut: wp.array(dtype=wp.int32),
    bits: int,
    groups: int,
    long_count: wp.array(dtype=wp.int32),
    listed: int,
    long_corner: wp.array(dtype=wp.int32),
    long_start: wp.array(dtype=wp.int64),
    long_best: wp.array(dtype=wp.int64),
):
    """Thread (g, k) searches subtree k of the cut (2^bits entries of the 4-wide view) for the long corners g,
    g + groups, ... (of the first `listed` at most) from each one's (bound, leaf), and keeps the least (distance,
    leaf) per corner: the order of `beats`, which the packed minimum keeps too. Every thread starts from the same
    (bound, leaf), so the result does not depend on the order the threads run in."""
    t = wp.tid()
    group = t >> bits
    entry = cut[t - (group << bits)]
    if entry < 0:
        return
    for item in range(group, wp.min(long_count[0], listed), groups):  # a dropped list counts -1
        p = _lattice_point(corner_keys[long_corner[item]], origin, cell)
        start_leaf = packed_leaf(long_start[item])
        leaf, leaf_sq = nearest_in_entry(bvh, p, entry, start_leaf, packed_distance_sq(long_start[item]))
        if leaf != start_leaf:
            atomic_min_packed(long_best, item, pack_distance_leaf(leaf_sq, leaf))


@wp.kernel(enable_backward=False)
def _gather_split(
    groups: int,
    long_count: wp.array(dtype=wp.int32),
    listed: int,
    long_corner: wp.array(dtype=wp.int32),
    long_best: wp.array(dtype=wp.int64),
    distance: wp.array(dtype=wp.float32),
    nearest: wp.array(dtype=wp.int32),
):
    """Write the split searches' results back to their corners (those that found a leaf within the band)."""
    for item in range(wp.tid(), wp.min(long_count[0], listed), groups):
        leaf = packed_leaf(long_best[item])
        if leaf >= 0:
            corner = long_corner[item]
            distance[corner] = wp.sqrt(packed_distance_sq(long_best[item]))
            nearest[corner] = leaf


def _make_sign_kernel(method: int) -> wp.Kernel:
    pseudonormal = method == SIGN_PSEUDONORMAL
    winding = method == SIGN_WINDING

    def sign_corners(
        corner_keys: wp.array(dtype=wp.int64),
        count: wp.array(dtype=wp.int32),
        capacity: int,
        origin: wp.vec3,
        cell: float,
        bvh: BvhView,
        sign: SignView,
        inside_by_winding_number: wp.array(dtype=wp.uint8),
        value: wp.array(dtype=wp.float32),
        nearest: wp.array(dtype=wp.int32),
    ):
        """Sign each corner's distance; where nothing lay within the band, the seed becomes its leaf. With
        winding numbers the sides come from `winding_kernel`, run beside the searches."""
        i = wp.tid()
        if i >= wp.min(count[0], capacity):
            return
        leaf = nearest[i]
        if leaf < 0:
            nearest[i] = -1 - leaf
        if wp.static(pseudonormal or winding):
            p = _lattice_point(corner_keys[i], origin, cell)
            inside = False
            if wp.static(pseudonormal):
                if leaf >= 0:
                    a, b, c = leaf_triangle(bvh, leaf)
                    closest, feature = closest_point_on_triangle(p, a, b, c)
                    inside = inside_by_pseudonormal(sign, bvh, p, bvh.leaf_face[leaf], closest, feature)
                else:
                    inside = inside_by_winding(bvh, p)
            if wp.static(winding):
                side = inside_by_winding_number[i]
                inside = side == WOUND_INSIDE
                if side == WOUND_CANCELLED:
                    inside = inside_by_winding(bvh, p)
            if inside:
                value[i] = -value[i]

    return wp.kernel(sign_corners, name=f"sign_corners_{method}", enable_backward=False, module="unique",
                     cuda_max_registers=SIGN_MAX_REGISTERS)


def winding_kernel() -> wp.Kernel:
    """Whether each corner is inside by its winding number (`wound_side`: corners where float32 cancelled are
    worked out again in float64 by the sign kernel, whose few registers do not hold up the searches). It
    needs only the corners and the refitted BVH,
    not the searches' nearest faces, so on CUDA it runs on a stream of its own beside them and fills the SMs
    that the searches' longest walks leave idle."""
    key = ("winding", SIGN_WINDING)
    if key not in _KERNELS:
        _KERNELS[key] = _make_winding_kernel()
    return _KERNELS[key]


def _make_winding_kernel() -> wp.Kernel:
    def sign_corners_by_winding(
        corner_keys: wp.array(dtype=wp.int64),
        count: wp.array(dtype=wp.int32),
        capacity: int,
        origin: wp.vec3,
        cell: float,
        bvh: BvhView,
        inside: wp.array(dtype=wp.uint8),
    ):
        i = wp.tid()
        if i >= wp.min(count[0], capacity):
            return
        inside[i] = wound_side(bvh, _lattice_point(corner_keys[i], origin, cell))

    return wp.kernel(sign_corners_by_winding, name="sign_corners_by_winding", enable_backward=False, module="unique",
                     cuda_max_registers=SIGN_MAX_REGISTERS)


def _make_query_kernel(method: int) -> wp.Kernel:
    pseudonormal = method == SIGN_PSEUDONORMAL
    winding = method == SIGN_WINDING
    unsigned = not (pseudonormal or winding)

    def inside_at(bvh: BvhView, sign: SignView, p: wp.vec3, face: int, closest: wp.vec3, feature: int,
                  in_domain: bool) -> bool:
        """The sign method's inside, for a point whose nearest face and closest point are known. Outside the
        domain (which holds the whole mesh) a point is outside a closed mesh; winding numbers are taken there
        too, as a soup of overlapping triangles can reach |w| > 1/2 beyond its bounding box."""
        inside = False
        if wp.static(winding):
            inside = inside_by_winding(bvh, p)
        if wp.static(pseudonormal):
            if in_domain:
                inside = inside_by_pseudonormal(sign, bvh, p, face, closest, feature)
        return inside

    def exact_normal(tree: OctreeView, corner_leaf: wp.array(dtype=wp.int32), node: int, octant: int,
                     bvh: BvhView, sign: SignView, p: wp.vec3, leaf: int, closest: wp.vec3, feature: int,
                     inside: bool, inv_side: float) -> wp.vec3:
        """The gradient of the signed distance at p, whose nearest face is `leaf`'s: away from the surface
        outside, towards it (outward) inside; on the surface (within float32's rounding of it), the closest
        feature's normal."""
        offset = p - closest
        length = wp.length(offset)
        if length * inv_side > _SURFACE_SNAP:
            n = offset / length
            if inside:
                n = -n
            return n
        n = wp.vec3(0.0)
        oriented = leaf
        if wp.static(pseudonormal):
            a, b, c = leaf_triangle(bvh, leaf)
            n = feature_normal(sign, bvh.leaf_face[leaf], feature_on_surface(closest, a, b, c, feature))
        if wp.length_sq(n) == 0.0:
            n, oriented = _surface_normal(tree, corner_leaf, node, octant, bvh, p, leaf)
        by_winding = wp.static(winding)
        if wp.static(pseudonormal):
            by_winding = sign.winding_frame[0] != 0  # a frame inside out, flat, or overlapping itself
        if by_winding:
            # outward for the winding numbers' inside, whichever way the face winds
            if _winds_inward(bvh, oriented, inv_side):
                n = -n
        return n

    inside_at = wp.func(inside_at, module="unique")
    exact_normal = wp.func(exact_normal, module="unique")

    def query_points(
        points: wp.array(dtype=wp.vec3),
        order: wp.array(dtype=wp.int32),
        ordered: int,
        offset: wp.vec3,
        to_local: float,
        turned: int,
        turn: wp.mat33,
        shift: wp.vec3,
        exact: int,
        outputs: int,
        tree: OctreeView,
        corner_value: wp.array(dtype=wp.float32),
        corner_leaf: wp.array(dtype=wp.int32),
        bvh: BvhView,
        sign: SignView,
        inv_side: float,
        band: float,
        out_distance: wp.array(dtype=wp.float32),
        out_closest: wp.array(dtype=wp.vec3),
        out_normal: wp.array(dtype=wp.vec3),
        out_face: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        if ordered != 0:  # the batch walked in its points' Morton order (PointQuery._order)
            i = order[i]
        p = _placed_point(points[i], offset, to_local, turned, turn, shift)
        resolution = 1 << tree.depth
        g = (p - tree.origin) / tree.cell
        top = float(resolution)
        in_domain = g[0] >= 0.0 and g[1] >= 0.0 and g[2] >= 0.0 and g[0] <= top and g[1] <= top and g[2] <= top
        # outside a region of interest the octree is coarse: such points are answered exactly
        low, high = tree.region_lower, tree.region_upper
        in_region = p[0] >= low[0] and p[1] >= low[1] and p[2] >= low[2] and p[0] <= high[0] and p[1] <= high[1]
        in_region = in_region and p[2] <= high[2]

        seed = int(-1)
        node = int(0)
        octant = int(0)
        if in_domain:
            cell = quantize(p, tree.origin, 1.0 / tree.cell, resolution)
            node, octant, level = locate(tree, cell)
            scale = 1 << (tree.depth - level)
            base = wp.vec3(
                float((cell[0] // scale) * scale), float((cell[1] // scale) * scale), float((cell[2] // scale) * scale)
            )
            t = (g - base) / float(scale)
            t = wp.vec3(wp.clamp(t[0], 0.0, 1.0), wp.clamp(t[1], 0.0, 1.0), wp.clamp(t[2], 0.0, 1.0))
            if exact == 0 and in_region:
                # trilinear interpolation of the leaf's corners, its gradient, and the corner nearest p
                value = float(0.0)
                grad = wp.vec3(0.0)
                heaviest = float(-1.0)
                nearest_corner = int(0)
                # beyond the band: all eight corners clamped to the same +-band, so the field is flat here
                first = corner_value[leaf_corner(tree, node, octant, 0)]
                flat = band > 0.0 and wp.abs(first) >= band
                # corners of both signs in a leaf the surface stays out of: an open mesh's winding number jumps
                # there, across an opening, and no interpolation follows the jump, so such a point is answered
                # exactly. The surface stays out of a leaf coarser than the finest level (every cell it touches
                # is refined), one with a corner farther from it than the leaf's diagonal, and one whose
                # corners are all farther than half of that (their empty balls cover the leaf).
                diagonal = 1.7320508 * float(scale) * tree.cell
                farthest = float(0.0)
                nearest = float(3.0e38)
                has_inside = False
                has_outside = False
                deepest = float(0.0)  # the largest |value| of the corners inside, and of those outside
                farthest_out = float(0.0)
                clamped = False
                for corner in range(8):
                    cx = float((corner >> 2) & 1)
                    cy = float((corner >> 1) & 1)
                    cz = float(corner & 1)
                    wx = cx * t[0] + (1.0 - cx) * (1.0 - t[0])
                    wy = cy * t[1] + (1.0 - cy) * (1.0 - t[1])
                    wz = cz * t[2] + (1.0 - cz) * (1.0 - t[2])
                    slot = leaf_corner(tree, node, octant, corner)
                    v = corner_value[slot]
                    if v != first:
                        flat = False
                    at_band = band > 0.0 and wp.abs(v) >= band
                    if at_band:
                        clamped = True
                    if wp.static(winding):
                        if v < 0.0:
                            has_inside = True
                            deepest = wp.max(deepest, -v)
                        else:
                            has_outside = True
                            farthest_out = wp.max(farthest_out, v)
                        if not at_band:  # a clamped value bounds nothing
                            farthest = wp.max(farthest, wp.abs(v))
                    nearest = wp.min(nearest, wp.abs(v))
                    weight = wx * wy * wz
                    value += weight * v
                    grad += v * wp.vec3((2.0 * cx - 1.0) * wy * wz, (2.0 * cy - 1.0) * wx * wz, (2.0 * cz - 1.0) * wx * wy)
                    if weight > heaviest:
                        heaviest = weight
                        nearest_corner = slot
                grad = grad / (float(scale) * tree.cell)
                length = wp.length(grad)
                unit = wp.vec3(0.0)
                if flat:
                    value = first  # not a weighted sum's rounding of it, and no gradient from that rounding
                beyond = band > 0.0 and wp.abs(value) >= band  # at the band: no face, no closest point, no normal
                if length > 0.0 and not beyond:
                    unit = grad / length
                # a leaf the medial surface crosses (mark_medial_leaves; marked for queries that ask for these)
                directed = (outputs & (_OUT_NORMAL | _OUT_CLOSEST)) != 0 and not beyond
                marked = directed and (tree.child_mask[node] >> (_MEDIAL_SHIFT + octant)) & 1 != 0
                if wp.static(unsigned):
                    # |d| interpolated across a sheet has a V-shaped valley whose gradient is zero or points
                    # towards the sheet within a cell of it; there the direction from p's nearest face is the
                    # normal (off the face: away from it; on it: the face's own), searched for (the corners'
                    # faces' directions lay nearly in the sheet). In a finest leaf the surface may cross, and in a
                    # marked leaf of any size: with refine="centroid" the surface crosses coarser ones too
                    if directed and ((scale == 1 and nearest <= diagonal) or marked):
                        near_leaf, foot, _feature = _nearest_point_from_corners(tree, corner_leaf, node, octant, bvh, p)
                        away = p - foot
                        away_length = wp.length(away)
                        if away_length * inv_side > _SURFACE_SNAP:
                            unit = away / away_length
                        else:
                            unit, _used = _surface_normal(tree, corner_leaf, node, octant, bvh, p, near_leaf)
                if wp.static(not unsigned):
                    # inside a sharp edge (wherever the medial surface runs) a leaf's corners took their values from
                    # faces that face apart, and the trilinear gradient there can point away from the surface: a
                    # penalty force along it pushes deeper. In such a leaf (marked by mark_medial_leaves) the normal
                    # is exact mode's. The distance and face stay the interpolation's, so no output depends on which
                    # others are asked for
                    if marked:
                        near_leaf, foot, feature = _nearest_point_from_corners(tree, corner_leaf, node, octant, bvh, p)
                        inside = inside_at(bvh, sign, p, bvh.leaf_face[near_leaf], foot, feature, True)
                        unit = exact_normal(tree, corner_leaf, node, octant, bvh, sign, p, near_leaf, foot, feature,
                                            inside, inv_side)
                # where a leaf's corners have their nearest points on opposite sides (a medial axis runs through
                # it) the interpolated gradient can shrink to nothing: points on the lattice there had a zero
                # normal and themselves as closest point. Such a point is answered exactly (whatever outputs
                # are asked for, so a distance does not depend on them)
                weak = length < _WEAK_GRADIENT and not beyond and not flat
                clear = scale > 1 or farthest > diagonal or nearest > 0.5 * diagonal
                # the jump also runs through finest leaves the surface crosses, beside an opening's rim: a signed
                # distance changes no faster than its argument where its sign does not jump, and no two corners
                # are farther apart than the diagonal, so a corner inside and one outside whose distances add up
                # to more than that straddle a jump (a clamped corner's band is less than its distance: it adds
                # no jump that is not there)
                jumps = clear or deepest + farthest_out > diagonal * (1.0 + _JUMP_SLACK)
                # every corner of a leaf the surface may cross clamped at the band says nothing of the surface,
                # which may still cross the leaf between them (a band narrower than a cell: an unsigned field read
                # points on its sheet as beyond the band): such a point is answered exactly. The surface may cross
                # a finest leaf, and under refine="centroid" a coarser one too (nineteenth outside check: 344 of
                # 5,000 points on a sphere read +band with no face)
                clamped_near = flat and (scale == 1 or tree.coarse_leaves_clear == 0)
                # a leaf with corners clamped at the band and others not reads too near inside it: a clamped
                # corner's +-band stands for a larger distance, so points beyond the band read inside it by up to
                # two cells (outside check, 2026-11-23). Such a point reading inside the band is answered exactly,
                # so band or not, ADF answers are the same after clamping, or exact
                short_of_band = clamped and not flat and not beyond
                # a leaf the rim crosses (mark_rim_leaves) holds both signs, whatever its corners read
                rim = False
                if wp.static(winding):
                    rim = (tree.child_mask[node] >> (_RIM_SHIFT + octant)) & 1 != 0
                if (not (has_inside and has_outside and jumps) and not weak and not clamped_near and not short_of_band
                        and not rim):
                    if outputs & _OUT_DISTANCE:
                        out_distance[i] = value
                    if outputs & _OUT_NORMAL:
                        out_normal[i] = unit
                    if outputs & _OUT_CLOSEST:
                        out_closest[i] = p - value * unit
                    if outputs & _OUT_FACE:
                        face = bvh.leaf_face[corner_leaf[nearest_corner]]
                        if beyond:
                            face = -1
                        out_face[i] = face
                    return
            # exact: start from the nearest of the faces recorded at the cell's corners
            seed = _nearest_corner_face(tree, corner_leaf, node, octant, bvh, p)
        else:
            seed = spatial_seed(bvh, p, tree.origin, inv_side)

        leaf, best_sq, finished = _nearest_past_ties(bvh, p, seed, band, UNLIMITED_VISITS)
        if leaf < 0:  # nothing within the band: +-band, by the winding number (no face to take a pseudonormal of)
            inside = False
            if wp.static(winding):
                inside = inside_by_winding(bvh, p)
            if wp.static(pseudonormal):
                if in_domain:
                    inside = inside_by_winding(bvh, p)
            if outputs & _OUT_DISTANCE:
                out_distance[i] = wp.where(inside, -band, band)
            if outputs & _OUT_NORMAL:
                out_normal[i] = wp.vec3(0.0)
            if outputs & _OUT_CLOSEST:
                out_closest[i] = wp.vec3(0.0)
            if outputs & _OUT_FACE:
                out_face[i] = -1
            return
        a, b, c = leaf_triangle(bvh, leaf)
        closest, feature = closest_point_on_triangle(p, a, b, c)
        face = bvh.leaf_face[leaf]
        d = wp.sqrt(best_sq)
        inside = inside_at(bvh, sign, p, face, closest, feature, in_domain)
        if outputs & _OUT_DISTANCE:
            out_distance[i] = wp.where(inside, -d, d)
        if outputs & _OUT_NORMAL:
            out_normal[i] = exact_normal(tree, corner_leaf, node, octant, bvh, sign, p, leaf, closest, feature,
                                         inside, inv_side)
        if outputs & _OUT_CLOSEST:
            out_closest[i] = closest
        if outputs & _OUT_FACE:
            out_face[i] = face

    capped = {} if QUERY_MAX_REGISTERS is None else {"cuda_max_registers": QUERY_MAX_REGISTERS}
    return wp.kernel(query_points, name=f"query_points_{method}", enable_backward=False, module="unique",
                     module_options=EXACT_ROUNDING, **capped)
