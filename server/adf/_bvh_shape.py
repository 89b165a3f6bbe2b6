"""A BVH's shape made on the host by the surface area heuristic (SAH), once, for the device to refit every frame.

The engine's other shape, Karras's radix tree over Morton codes (`Bvh.build`), is linked on the device in a few
kernels, but splits where the codes' bits change, not where the triangles leave space between them. A tree whose
boxes overlap less is opened less: on an H200 (2026-12-01, `badf bench engine`) the distances of the armadillo's
depth-7 update took 0.79 ms on this shape against 1.01 on Morton's, the bunny's 1.30 against 1.40, with the same
answers (docs/engine.md, "The BVH's shape"). Only a frame's boxes change
(the refit), so a shape made once from the first frame serves every frame after, and moving the domain keeps it.

The tree is built top-down: each range of triangles is cut on the longest axis of its centroids' bounds, into 32
even bins (a range of at most 32 triangles: one bin per triangle, in their order along the axis), and split between
the two bins where the areas of the two sides' boxes, each times its triangle count, sum least. The builder is a
Warp kernel on the CPU back-end, whatever the object's device (Warp's CPU compiler, which every warp-lang wheel
carries, compiles it once; the kernel cache keeps it): one thread splits the top of the tree, and the subtrees
below it are built side by side by the CPU back-end's threads (`cpu_threads`), into the same tree. On this
project's 2-core host (2026-12-01) it made the bunny's tree (69,451 triangles) in 59 to 64 ms with two threads and
84 to 87 with one, the armadillo's (86,482) in 69 to 70 and 109 to 114, where the same passes in numpy, every range
of a level at once, took 520 to 600 and 640 to 720. The trees were the numpy
builder's node for node for the bunny, the armadillo and spot; fandisk's, homer's and the rocker arm's differed in
48, 1 and 3 of their nodes, where two cuts cost the same to within rounding (the trees' summed areas agree to
5e-6). Its arithmetic is float64, on coordinates scaled by a power of two to about unit size.

The result is the radix tree's layout, which the rest of the BVH reads: internal nodes 0..n-2 (0 the root), leaf
k being the k-th triangle of `order` (node n - 1 + k), each internal node's leaves a range first..last of it.
Nodes are numbered in preorder, so that a subtree's nodes lie together in memory (as the radix tree's do, by their
ranges).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import warp as wp

from badf.server.adf._inputs import InvalidInputError
from badf.server.adf._threads import cpu_threads, shared_pool

BINS = 32
_BINS = wp.constant(BINS)
# A leaf at most this deep: the searches' stacks hold a binary tree of 62 levels (_bvh.WIDE_STACK_DEPTH). A range
# is split by area only where both sides can still be split evenly down to single triangles within it.
MAX_DEPTH = 60
# Below the top of the tree, subtrees are built side by side: those of at most n / (_SUBTREES_PER_THREAD threads)
# triangles, or of _SHARED_GRAIN where that is more
_SHARED_GRAIN = 1024
_SUBTREES_PER_THREAD = 4


class Shape(NamedTuple):
    order: np.ndarray  # (n,) int32: the face of each leaf
    left: np.ndarray  # (n - 1,) int32: child ids (internal i, or leaf k as n - 1 + k)
    right: np.ndarray
    first: np.ndarray  # (n - 1,) int32: each internal node's first and last leaf
    last: np.ndarray
    depth: int  # levels from the root to the deepest leaf


def resolve_shape(requested: str, on_cpu: bool) -> str:
    """The shape `bvh="auto"` takes: SAH on the CPU back-end, Morton's on CUDA.

    A CPU launch's cost is its total work, which an SAH tree's shorter walks cut: objects on either shape alternated
    on a 2-core host (2026-12-01, bench/probes/probe_bvh_shapes.py, the bunny, the armadillo and spot at depths 5 and
    7) updated 3 to 10% faster and answered exact queries 10 to 20% faster on it, and registered 5 to 12% slower at
    depth 5 and about as fast at depth 7, where the first frame's searches win the shape's time back. On an H200 the
    radix tree is linked on the device within the build, and the shape's 40 to 60 ms of host time take 150 to 500
    frames to win back (docs/engine.md, "The BVH's shape").

    The SAH tree is made by a kernel on Warp's CPU back-end whatever the object's device, so a Warp that cannot run
    it (installed without its CPU compiler) refuses "sah" here, before anything is built."""
    if requested == "sah" and not wp.is_cpu_available():
        raise InvalidInputError("bvh='sah' makes its tree on Warp's CPU back-end, which this Warp cannot run (its CPU "
                                "compiler, warp-clang, is missing); use bvh='morton' or 'auto'")
    if requested != "auto":
        return requested
    return "sah" if on_cpu else "morton"


def sah_shape(vertices: np.ndarray, faces: np.ndarray, *, threads: int | None = None) -> Shape:
    """The SAH tree of the triangles `vertices[faces]` (n >= 2). The top of the tree is split by one thread; the
    subtrees below it are shared out over `threads` (default: the CPU back-end's, `cpu_threads`), which changes
    nothing in the tree."""
    v = np.asarray(vertices, np.float64)
    # scaled by a power of two (exact) to about unit size, so that no area overflows or underflows float64
    scale = 2.0 ** -np.frexp(max(float(np.abs(v).max()), 1e-300))[1]
    n = len(faces)
    threads = cpu_threads() if threads is None else threads

    def room(shape, dtype=wp.int32):
        return wp.empty(shape, dtype=dtype, device="cpu")

    def triangles() -> _Triangles:
        t = _Triangles()
        t.face, t.lower, t.upper, t.centre = room(n), room(n, wp.vec3d), room(n, wp.vec3d), room(n, wp.vec3d)
        return t

    at, spare = triangles(), triangles()
    wp.launch(_triangle_boxes, dim=n, device="cpu", inputs=[
        wp.array(v * scale, dtype=wp.vec3d, device="cpu"),
        wp.array(np.asarray(faces, np.int32), dtype=wp.vec3i, device="cpu"), at])
    tree = [room(n - 1) for _ in range(4)]  # left, right, first, last
    bin_of, stack = room(n), room((n, 4))
    # ranges left for the subtrees' threads: at most one per two triangles, as each holds two or more
    deferred, deferred_count = room((n // 2 + 1, 4)), wp.zeros(1, dtype=wp.int32, device="cpu")
    grain = 0 if threads <= 1 else max(_SHARED_GRAIN, n // (_SUBTREES_PER_THREAD * threads))

    def build(ranges: wp.array, first: int, last: int, grain: int) -> int:
        """Split ranges[first:last] and their descendants, leaving those of at most `grain` triangles (0: none) to
        `deferred`; returns the deepest leaf's depth."""
        deepest = wp.zeros(1, dtype=wp.int32, device="cpu")
        wp.launch(_build, dim=1, device="cpu", inputs=[
            at, spare, MAX_DEPTH, ranges, first, last, grain, deferred, deferred_count, stack, bin_of,
            room(BINS), room((BINS, 4), wp.vec3d), room(BINS, wp.float64), *tree, deepest])
        return int(deepest.numpy()[0])

    root = wp.array(np.array([[0, n, 0, 0]], np.int32), dtype=wp.int32, device="cpu")
    depth = build(root, 0, 1, grain)
    left_over = int(deferred_count.numpy()[0])
    if left_over:
        # groups of deferred ranges of about equal triangle counts, a launch each, side by side from the pool
        counts = np.cumsum(deferred.numpy()[:left_over, 1])
        groups = min(left_over, _SUBTREES_PER_THREAD * threads)
        bounds = np.unique(np.searchsorted(counts, counts[-1] * np.arange(1, groups) / groups, side="right"))
        edges = [0, *[int(e) for e in bounds if 0 < e < left_over], left_over]
        pool = shared_pool(threads)
        futures = [pool.submit(build, deferred, edges[j], edges[j + 1], 0) for j in range(len(edges) - 1)]
        depth = max([depth, *(future.result() for future in futures)])
    return Shape(at.face.numpy(), *(array.numpy() for array in tree), depth)


@wp.struct
class _Triangles:
    """Triangles by their place in the tree's order, each with its box and centroid: a range's are side by side,
    so that the passes over it read memory in order."""

    face: wp.array(dtype=wp.int32)
    lower: wp.array(dtype=wp.vec3d)
    upper: wp.array(dtype=wp.vec3d)
    centre: wp.array(dtype=wp.vec3d)


@wp.kernel(enable_backward=False)
def _triangle_boxes(vertices: wp.array(dtype=wp.vec3d), faces: wp.array(dtype=wp.vec3i), out: _Triangles):
    i = wp.tid()
    a = vertices[faces[i][0]]
    b = vertices[faces[i][1]]
    c = vertices[faces[i][2]]
    out.face[i] = i
    out.lower[i] = wp.min(wp.min(a, b), c)
    out.upper[i] = wp.max(wp.max(a, b), c)
    out.centre[i] = (a + b + c) / wp.float64(3.0)


@wp.func
def _move(src: _Triangles, i: int, dst: _Triangles, j: int):
    dst.face[j] = src.face[i]
    dst.lower[j] = src.lower[i]
    dst.upper[j] = src.upper[i]
    dst.centre[j] = src.centre[i]


@wp.func
def _half_area(lo: wp.vec3d, hi: wp.vec3d) -> wp.float64:
    d = hi - lo
    return d[0] * d[1] + d[1] * d[2] + d[2] * d[0]


@wp.func
def _log2_ceil(x: int) -> int:
    k = int(0)
    while (1 << k) < x:
        k += 1
    return k


@wp.func
def _split(at: _Triangles, spare: _Triangles, bin_of: wp.array(dtype=wp.int32), in_bin: wp.array(dtype=wp.int32),
           boxes: wp.array2d(dtype=wp.vec3d), along_of: wp.array(dtype=wp.float64), begin: int, count: int,
           depth: int, max_depth: int) -> int:
    """The range's left count, with its triangles reordered within it by bin where it is cut by area. Scratch:
    `spare` and `bin_of` per place, `in_bin` per bin, `boxes` per bin (its box, then the box of it and every bin
    right of it: lower and upper each), `along_of` the positions along the axis in a range of at most BINS."""
    halves = count // 2
    c_lo = at.centre[begin]
    c_hi = c_lo
    for i in range(begin + 1, begin + count):
        c_lo = wp.min(c_lo, at.centre[i])
        c_hi = wp.max(c_hi, at.centre[i])
    size = c_hi - c_lo
    axis = int(0)
    if size[1] > size[axis]:
        axis = 1
    if size[2] > size[axis]:
        axis = 2
    width = size[axis]
    if count <= 2 or width <= wp.float64(0.0):
        return halves
    bins = wp.min(_BINS, count)
    inverse = wp.float64(1.0) / width
    empty_lo = wp.vec3d(wp.float64(wp.inf), wp.float64(wp.inf), wp.float64(wp.inf))
    if count <= _BINS:
        # a bin per triangle, in their order along the axis (ties as they came: an insertion sort, which a range
        # cut on the same axis as its parent's passes in one sweep), so that every cut between two of them is tried
        for i in range(count):
            _move(at, begin + i, spare, begin)
            along = (spare.centre[begin][axis] - c_lo[axis]) * inverse
            j = i
            while j > 0 and along_of[j - 1] > along:
                along_of[j] = along_of[j - 1]
                _move(at, begin + j - 1, at, begin + j)
                j -= 1
            along_of[j] = along
            _move(spare, begin, at, begin + j)
        for b in range(count):
            in_bin[b] = b + 1
            boxes[b, 0] = at.lower[begin + b]
            boxes[b, 1] = at.upper[begin + b]
    else:
        # even bins along the axis, each with its count and box; then a stable counting sort of the range by bin
        for b in range(bins):
            in_bin[b] = 0
            boxes[b, 0] = empty_lo
            boxes[b, 1] = -empty_lo
        for i in range(begin, begin + count):
            b = wp.min(int((at.centre[i][axis] - c_lo[axis]) * inverse * wp.float64(bins)), bins - 1)
            bin_of[i] = b
            in_bin[b] += 1
            boxes[b, 0] = wp.min(boxes[b, 0], at.lower[i])
            boxes[b, 1] = wp.max(boxes[b, 1], at.upper[i])
        placed = int(0)
        for b in range(bins):
            placed += in_bin[b]
            in_bin[b] = placed - in_bin[b]  # where the bin starts, then (after the scatter) where the next one does
        for i in range(begin, begin + count):
            b = bin_of[i]
            _move(at, i, spare, begin + in_bin[b])
            in_bin[b] += 1
        for i in range(begin, begin + count):
            _move(spare, i, at, i)
    # in_bin[b] now counts the triangles in bins 0..b; the boxes of bins b.. from the right
    boxes[bins - 1, 2] = boxes[bins - 1, 0]
    boxes[bins - 1, 3] = boxes[bins - 1, 1]
    for k in range(bins - 1):
        b = bins - 2 - k
        boxes[b, 2] = wp.min(boxes[b, 0], boxes[b + 1, 2])
        boxes[b, 3] = wp.max(boxes[b, 1], boxes[b + 1, 3])
    # a cut after each bin but the last: cost = area(left) * n_left + area(right) * n_right, the first least
    best = wp.float64(wp.inf)
    split = halves
    lo = empty_lo
    hi = -empty_lo
    for b in range(bins - 1):
        lo = wp.min(lo, boxes[b, 0])
        hi = wp.max(hi, boxes[b, 1])
        n_left = in_bin[b]
        n_right = count - n_left
        if n_left > 0 and n_right > 0:
            cost = _half_area(lo, hi) * wp.float64(n_left) + _half_area(boxes[b + 1, 2], boxes[b + 1, 3]) * wp.float64(
                n_right)
            if cost < best:
                best = cost
                split = n_left
    # both sides must still reach single triangles by even splits within max_depth levels
    if depth + 1 + _log2_ceil(wp.max(split, count - split)) > max_depth:
        return halves
    return split


@wp.kernel(enable_backward=False)
def _build(at: _Triangles, spare: _Triangles, max_depth: int, ranges: wp.array2d(dtype=wp.int32), first_range: int,
           last_range: int, grain: int, deferred: wp.array2d(dtype=wp.int32), deferred_count: wp.array(dtype=wp.int32),
           stack: wp.array2d(dtype=wp.int32), bin_of: wp.array(dtype=wp.int32), in_bin: wp.array(dtype=wp.int32),
           boxes: wp.array2d(dtype=wp.vec3d), along_of: wp.array(dtype=wp.float64), left: wp.array(dtype=wp.int32),
           right: wp.array(dtype=wp.int32), first: wp.array(dtype=wp.int32), last: wp.array(dtype=wp.int32),
           deepest: wp.array(dtype=wp.int32)):
    """One thread: each of the ranges first_range..last_range - 1 split to single triangles, a range and the ones
    still to split on a stack, each (begin, count, depth, and how many times the path from the root to it turns
    right). With a grain, a range of at most that many triangles is left in `deferred` instead. A range's stack
    lies in the stack's rows from its begin on: a subtree of c triangles holds at most c - 1 ranges at once, so
    the threads building disjoint ranges keep apart.

    Nodes are numbered in preorder. The internal nodes before a node are its ancestors and those of the subtrees
    left of its path, which hold its first leaf's count of leaves in as many subtrees as right turns: its id is
    begin + depth - turns, wherever it is built."""
    n = at.face.shape[0]
    for r in range(first_range, last_range):
        base = ranges[r, 0]
        for k in range(4):
            stack[base, k] = ranges[r, k]
        top = int(1)
        while top > 0:
            top -= 1
            begin = stack[base + top, 0]
            count = stack[base + top, 1]
            depth = stack[base + top, 2]
            turns = stack[base + top, 3]
            if count <= grain:
                slot = wp.atomic_add(deferred_count, 0, 1)
                deferred[slot, 0] = begin
                deferred[slot, 1] = count
                deferred[slot, 2] = depth
                deferred[slot, 3] = turns
                continue
            node = begin + depth - turns
            first[node] = begin
            last[node] = begin + count - 1
            deepest[0] = wp.max(deepest[0], depth + 1)
            split = _split(at, spare, bin_of, in_bin, boxes, along_of, begin, count, depth, max_depth)
            # the right side is pushed first, so that the left is split next
            for side in range(2):
                side_begin = begin + split
                side_count = count - split
                side_turns = turns + 1
                if side == 1:
                    side_begin = begin
                    side_count = split
                    side_turns = turns
                child = n - 1 + side_begin
                if side_count > 1:
                    child = side_begin + depth + 1 - side_turns
                    stack[base + top, 0] = side_begin
                    stack[base + top, 1] = side_count
                    stack[base + top, 2] = depth + 1
                    stack[base + top, 3] = side_turns
                    top += 1
                if side == 0:
                    right[node] = child
                else:
                    left[node] = child
