"""Probe, not part of the product (python3 bench/probes/probe_persistent.py MESH.npz [device]): corner
searches by persistent threads that take corners one at a time from a shared counter, stop after a budget
of node visits and list the rest for the subtree split (the engine's _split_searches), against the engine's
own kernel, one thread per corner. It searches the binary tree's subtrees, whose boxes the engine no longer
keeps (dropped after 2f9483c): check out 2f9483c to run it."""
import sys
import time

import numpy as np
import warp as wp

from badf.server.adf import _distance as D
from badf.server.adf._bvh import BvhView
from badf.server.adf._geometry import pack_distance_leaf

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search  # noqa: E402

@wp.kernel(enable_backward=False)
def persistent(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int, origin: wp.vec3,
               cell: float, inv_side: float, depth: int, bvh: BvhView, band: float, coherent: int,
               previous_keys: wp.array(dtype=wp.int64), previous_face: wp.array(dtype=wp.int32),
               previous_count: wp.array(dtype=wp.int32), previous_capacity: int, previous_origin: wp.vec3,
               previous_inv_cell: float, budget: int, next_item: wp.array(dtype=int),
               distance: wp.array(dtype=float), nearest: wp.array(dtype=int), long_count: wp.array(dtype=int),
               long_corner: wp.array(dtype=int), long_start: wp.array(dtype=wp.int64), long_best: wp.array(dtype=wp.int64)):
    n = wp.min(count[0], capacity)
    i = wp.atomic_add(next_item, 0, 1)
    while i < n:
        p = D._lattice_point(corner_keys[i], origin, cell)
        seed = D.coherent_seed(bvh, p, depth, previous_keys, previous_face, previous_count, previous_capacity,
                               previous_origin, previous_inv_cell)
        best_leaf, best_sq, finished = D._nearest_with_band_budgeted(bvh, p, seed, band, budget)
        distance[i] = wp.sqrt(best_sq)
        nearest[i] = best_leaf
        if not finished:
            D.list_long_search(i, best_sq, best_leaf, capacity, long_count, long_corner, long_start, long_best)
        i = wp.atomic_add(next_item, 0, 1)


@wp.kernel(enable_backward=False)
def split_pairs(corner_keys: wp.array(dtype=wp.int64), origin: wp.vec3, cell: float, bvh: BvhView,
                cut: wp.array(dtype=wp.int32), levels: int, next_pair: wp.array(dtype=int),
                long_count: wp.array(dtype=wp.int32), long_corner: wp.array(dtype=wp.int32),
                long_start: wp.array(dtype=wp.int64), long_best: wp.array(dtype=wp.int64)):
    """Persistent threads over (long corner, cut subtree) pairs, taken one at a time from a shared counter:
    consecutive pairs share a corner, so a warp walks 32 subtrees around one point."""
    total = long_count[0] << levels
    k = wp.atomic_add(next_pair, 0, 1)
    while k < total:
        item = k >> levels
        slot = cut[k - (item << levels)]
        if slot >= 0:
            p = D._lattice_point(corner_keys[long_corner[item]], origin, cell)
            start_leaf = D.packed_leaf(long_start[item])
            leaf, leaf_sq = D.nearest_in_slot(bvh, p, slot, start_leaf, D.packed_distance_sq(long_start[item]))
            if leaf != start_leaf:
                D.atomic_min_packed(long_best, item, pack_distance_leaf(leaf_sq, leaf))
        k = wp.atomic_add(next_pair, 0, 1)


DEV = sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
field, inputs, n, truth = captured_search(sys.argv[1], DEV)
cap, cell = inputs[2], inputs[4]
keys, origin, bvh = inputs[0], inputs[3], inputs[7]
z = lambda dt: wp.zeros(cap, dtype=dt, device=DEV)
dist, near, lc, lb, lbest = z(float), z(int), z(int), z(wp.int64), z(wp.int64)
lcount = wp.zeros(1, dtype=int, device=DEV)
counter = wp.zeros(1, dtype=int, device=DEV)
unseeded = wp.zeros(1, dtype=int, device=DEV)
sms = wp.get_device(DEV).sm_count if DEV != "cpu" else 1
UNL = 2**31 - 1
cases = [("one per corner", D.corner_searches, cap, UNL, 6, False),
         ("one per corner", D.corner_searches_budgeted, cap, 128, 6, False)]
for budget in (32, 64, 128):
    for levels in (4, 6, 8):
        cases.append(("persistent 2048/SM, pair split", persistent, sms * 2048, budget, levels, True))
        cases.append(("one per corner, pair split", D.corner_searches_budgeted, cap, budget, levels, True))
counter2 = wp.zeros(1, dtype=int, device=DEV)
for name, kernel, threads, budget, levels, pairs in cases:
    cut = field._bvh.cut(levels)
    groups = 4096
    times = []
    for rep in range(5):
        wp.synchronize()
        lcount.zero_(); counter.zero_(); counter2.zero_()
        c0 = time.perf_counter()
        if DEV != "cpu":
            e0, e1, e2 = (wp.Event(enable_timing=True) for _ in range(3))
            wp.record_event(e0)
        # the engine's kernel (one thread per corner) seeds each search itself: seeded 0
        extra = [counter] if kernel is persistent else [0, unseeded, unseeded]
        wp.launch(kernel, dim=threads, inputs=inputs + [budget] + extra, outputs=[dist, near, lcount, lc, lb, lbest],
                  device=DEV, block_dim=128)
        c1 = time.perf_counter()
        if DEV != "cpu":
            wp.record_event(e1)
        if pairs:
            wp.launch(split_pairs, dim=sms * 2048, inputs=[keys, origin, cell, bvh, cut, levels, counter2, lcount, lc, lb],
                      outputs=[lbest], device=DEV, block_dim=128)
        else:
            wp.launch(D._split_searches, dim=groups << levels, inputs=[keys, origin, cell, bvh, cut, levels, groups, lcount, cap, lc, lb],
                      outputs=[lbest], device=DEV)
        wp.launch(D._gather_split, dim=groups, inputs=[groups, lcount, cap, lc, lbest], outputs=[dist, near], device=DEV)
        if DEV != "cpu":
            wp.record_event(e2)
        wp.synchronize()
        c2 = time.perf_counter()
        times.append(((c1 - c0) * 1e3, (c2 - c1) * 1e3) if DEV == "cpu" else
                     (wp.get_event_elapsed_time(e0, e1), wp.get_event_elapsed_time(e1, e2)))
    t = np.median(np.array(times), axis=0)
    err = float(np.abs(dist.numpy()[:n] - truth).max() / field._domain.local_side)
    print(dict(kernel=name, pair_split=pairs, threads=threads, budget=budget if budget < UNL else "none", levels=levels,
               long=int(lcount.numpy()[0]), searches_ms=round(float(t[0]), 4), split_ms=round(float(t[1]), 4),
               total_ms=round(float(t.sum()), 4), max_err_side=err), flush=True)
