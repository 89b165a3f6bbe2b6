"""A BVH's shape made on the host by the surface area heuristic (SAH), once, for the device to refit every frame.

The engine's other shape, Karras's radix tree over Morton codes (`Bvh.build`), is linked on the device in a few
kernels, but splits where the codes' bits change, not where the triangles leave space between them. A tree whose
boxes overlap less is opened less: on an H200 (2026-11-29, bench/probes/probe_sah_tree.py) the bunny's searches and
winding numbers took 1.06 ms of a depth-7 update on this shape against 1.34 on Morton's, with the same distances
(docs/engine.md, "The BVH's shape"). Only a frame's boxes change
(the refit), so a shape made once from the first frame serves every frame after, and moving the domain keeps it.

The tree is built top-down a level at a time, every range of the level at once in numpy: each range is cut on
the longest axis of its centroids' bounds, into 32 even bins (a range of at most 32 triangles: one bin per triangle,
in their order along the axis), and split between the two bins where the areas of the two sides' boxes, each times
its triangle count, sum least.

The result is the radix tree's layout, which the rest of the BVH reads: internal nodes 0..n-2 (0 the root), leaf
k being the k-th triangle of `order` (node n - 1 + k), each internal node's leaves a range first..last of it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

BINS = 32
# A leaf at most this deep: the searches' stacks hold a binary tree of 62 levels (_bvh.WIDE_STACK_DEPTH). A range
# is split by area only where both sides can still be split evenly down to single triangles within it.
MAX_DEPTH = 60


class Shape(NamedTuple):
    order: np.ndarray  # (n,) int32: the face of each leaf
    left: np.ndarray  # (n - 1,) int32: child ids (internal i, or leaf k as n - 1 + k)
    right: np.ndarray
    first: np.ndarray  # (n - 1,) int32: each internal node's first and last leaf
    last: np.ndarray
    depth: int  # levels from the root to the deepest leaf


def sah_shape(vertices: np.ndarray, faces: np.ndarray) -> Shape:
    """The SAH tree of the triangles `vertices[faces]` (n >= 2)."""
    corners = np.asarray(vertices, np.float64)[faces]
    lower, upper = corners.min(axis=1), corners.max(axis=1)
    # in a unit box, so that the running minima's offsets (_running_min) are far larger than any coordinate
    origin, scale = lower.min(axis=0), 1.0 / max(float((upper.max(axis=0) - lower.min(axis=0)).max()), 1e-300)
    lower, upper = (lower - origin) * scale, (upper - origin) * scale
    centre = (corners.mean(axis=1) - origin) * scale
    box = np.hstack([lower, -upper])
    n = len(faces)
    order = np.arange(n)
    left, right = np.empty(n - 1, np.int32), np.empty(n - 1, np.int32)
    first, last = np.empty(n - 1, np.int32), np.empty(n - 1, np.int32)
    # the ranges still to split, each an internal node: begin, count, depth, and how many times the path from the
    # root to it turns right. Nodes are numbered in preorder, so that a subtree's nodes lie together in memory (as
    # the radix tree's do, by their ranges): the internal nodes before a node are its ancestors and those of the
    # subtrees left of its path, which hold its first leaf's count of leaves in as many subtrees as right turns.
    begin, count = np.array([0]), np.array([n])
    depth, turns = np.array([0]), np.array([0])
    deepest = 0
    while len(begin):
        node = begin + depth - turns
        first[node], last[node] = begin, begin + count - 1
        split = _split(order, begin, count, depth, box, centre)
        sides = ((begin, split, turns), (begin + split, count - split, turns + 1))
        children = []
        ranges = []
        for side_begin, side_count, side_turns in sides:
            inner = side_count > 1
            children.append(np.where(inner, side_begin + depth + 1 - side_turns, n - 1 + side_begin))
            ranges.append((side_begin[inner], side_count[inner], depth[inner] + 1, side_turns[inner]))
        left[node], right[node] = children
        deepest = max(deepest, int(depth.max()) + 1)
        begin, count, depth, turns = (np.concatenate(parts) for parts in zip(*ranges))
    return Shape(order.astype(np.int32), left, right, first, last, deepest)


def _split(order, begin, count, depth, box, centre) -> np.ndarray:
    """Each range's left count (reordering `order` within the ranges cut by area, left side first). `box` is each
    triangle's (lower, -upper), so that one running minimum merges both."""
    ranges = len(begin)
    starts = np.cumsum(count) - count  # of each range among the positions taken here
    at = np.repeat(begin - starts, count) + np.arange(int(count.sum()))  # positions in order
    of = np.repeat(np.arange(ranges), count)  # range of each
    ids = order[at]
    c = centre[ids]
    c_lo, c_hi = np.minimum.reduceat(c, starts), np.maximum.reduceat(c, starts)
    axis = np.argmax(c_hi - c_lo, axis=1)
    width = (c_hi - c_lo)[np.arange(ranges), axis]
    halves = count // 2
    by_area = (count > 2) & (width > 0)
    bins = np.where(by_area, np.minimum(BINS, count), 1)
    # where along the range's axis each centroid lies, 0 to 1
    along = (c[np.arange(len(ids)), axis[of]] - c_lo[of, axis[of]]) * np.divide(1.0, width, out=np.zeros(ranges),
                                                                                where=width > 0)[of]
    bin_of = np.minimum((along * bins[of]).astype(np.int64), bins[of] - 1)
    # a range of at most BINS triangles takes each in a bin of its own, in their order along the axis: every cut
    # between two of them is tried, where even bins would put several in one and try fewer
    few = (by_area & (count <= BINS))[of]
    if few.any():
        ranked = np.argsort(of + np.minimum(along, 0.999999), kind="stable")
        rank = np.empty(len(ids), np.int64)
        rank[ranked] = np.arange(len(ids)) - starts[of[ranked]]
        bin_of = np.where(few, rank, bin_of)
    group_start = np.cumsum(bins) - bins
    group = group_start[of] + bin_of  # ascending within each range
    sorted_ids = ids[np.argsort(group, kind="stable")]
    order[at] = sorted_ids  # bins in order within each range; a range in one bin keeps its order
    groups = int(bins.sum())
    in_group = np.bincount(group, minlength=groups)
    # each bin's box (an empty bin's reads its neighbour's from reduceat, and is emptied after)
    g_box = np.minimum.reduceat(box[sorted_ids], np.minimum(np.cumsum(in_group) - in_group, len(ids) - 1))
    g_box[in_group == 0] = np.inf
    range_of_group = np.repeat(np.arange(ranges), bins)
    # the boxes of bins 0..k and of bins k+1.. of each range, and the counts on the left
    left = _running_min(g_box, range_of_group)
    right = _running_min(g_box[::-1], ranges - 1 - range_of_group[::-1])[::-1]
    on_left = np.cumsum(in_group) - np.repeat(starts, bins)
    # a cut after each bin but a range's last: cost = area(left) * n_left + area(right) * n_right
    cut = np.ones(groups, bool)
    cut[group_start + bins - 1] = False
    candidates = np.flatnonzero(cut)
    n_left = on_left[candidates]
    n_right = count[range_of_group[candidates]] - n_left
    cost = np.full(groups, np.inf)
    cost[candidates] = _half_area(left[candidates]) * n_left + _half_area(right[candidates + 1]) * n_right
    cost[candidates[(n_left == 0) | (n_right == 0)]] = np.inf
    best_cost = np.minimum.reduceat(cost, group_start)
    best = np.minimum.reduceat(np.where(cost == best_cost[range_of_group], np.arange(groups), groups), group_start)
    split = np.where(by_area & np.isfinite(best_cost), on_left[np.minimum(best, groups - 1)], halves)
    # both sides must still reach single triangles by even splits within MAX_DEPTH levels
    fits = depth + 1 + _log2_ceil(np.maximum(split, count - split)) <= MAX_DEPTH
    return np.where(fits, split, halves)


def _running_min(values: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """The running minimum of `values` (G, 6) within each run of equal, ascending `segment`: each segment is
    offset below every earlier one, so one scan over all of them restarts at each (values lie in [-1, 1] or are
    infinite). The offsets round the boxes by 1e-10 at most, which only the heuristic's costs see."""
    offset = 4.0 * segment[:, None]
    return np.minimum.accumulate(values - offset, axis=0) + offset


def _half_area(box: np.ndarray) -> np.ndarray:
    d = -box[:, 3:] - box[:, :3]
    return d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0]


def _log2_ceil(x: np.ndarray) -> np.ndarray:
    return np.ceil(np.log2(np.maximum(x, 1))).astype(np.int64)
