"""Probe, not part of the product (python3 bench/probes/probe_split.py MESH.npz [device]; results in
docs/results/probe-split-*): corner searches where corners far from the surface last frame go
straight to the subtree split, and the rest search whole (or with a budget). It searches the binary tree's
subtrees, whose boxes the engine no longer keeps (dropped after 2f9483c): check out 2f9483c to run it."""
import sys
import time

import numpy as np
import warp as wp

from badf.server.adf import _distance as D
from badf.server.adf._bvh import BvhView

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search  # noqa: E402

@wp.kernel(enable_backward=False)
def searches(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int, origin: wp.vec3,
             cell: float, inv_side: float, depth: int, bvh: BvhView, band: float, coherent: int,
             previous_keys: wp.array(dtype=wp.int64), previous_face: wp.array(dtype=wp.int32),
             previous_count: wp.array(dtype=wp.int32), previous_capacity: int, previous_origin: wp.vec3,
             previous_inv_cell: float, budget: int, far: wp.array(dtype=int),
             distance: wp.array(dtype=float), nearest: wp.array(dtype=int), long_count: wp.array(dtype=int),
             long_corner: wp.array(dtype=int), long_start: wp.array(dtype=wp.int64), long_best: wp.array(dtype=wp.int64)):
    i = wp.tid()
    if i >= wp.min(count[0], capacity):
        return
    p = D._lattice_point(corner_keys[i], origin, cell)
    seed = D.coherent_seed(bvh, p, depth, previous_keys, previous_face, previous_count, previous_capacity,
                           previous_origin, previous_inv_cell)
    b = budget
    if far[i] != 0:
        b = 0
    best_leaf, best_sq, finished = D._nearest_with_band_budgeted(bvh, p, seed, band, b)
    distance[i] = wp.sqrt(best_sq)
    nearest[i] = best_leaf
    if not finished:
        D.list_long_search(i, best_sq, best_leaf, capacity, long_count, long_corner, long_start, long_best)

DEV = sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
field, inputs, n, truth = captured_search(sys.argv[1], DEV)
cap, cell = inputs[2], inputs[4]
keys, origin, bvh = inputs[0], inputs[3], inputs[7]
cells = truth / cell
z = lambda dt: wp.zeros(cap, dtype=dt, device=DEV)
dist, near, lc, lb, lbest = z(float), z(int), z(int), z(wp.int64), z(wp.int64)
lcount = wp.zeros(1, dtype=int, device=DEV)
far = z(int)
rows = []
for K, budget, levels in [(None, 2**31 - 1, 6), (None, 128, 6), (8, 2**31 - 1, 6), (4, 2**31 - 1, 6), (8, 128, 6),
                          (4, 128, 6), (8, 2**31 - 1, 8), (4, 128, 8), (2, 128, 8), (4, 256, 6)]:
    flags = np.zeros(cap, np.int32)
    if K is not None:
        flags[:n] = cells >= K
    far.assign(flags)
    cut = field._bvh.cut(levels)
    groups = 4096
    times = []
    for rep in range(5):
        wp.synchronize()
        cpu = DEV == "cpu"
        if not cpu:
            e0 = wp.Event(enable_timing=True); e1 = wp.Event(enable_timing=True); e2 = wp.Event(enable_timing=True)
        lcount.zero_()
        c0 = time.perf_counter()
        if not cpu: wp.record_event(e0)
        wp.launch(searches, dim=cap, inputs=inputs + [budget, far], outputs=[dist, near, lcount, lc, lb, lbest],
                  device=DEV, block_dim=128)
        c1 = time.perf_counter()
        if not cpu: wp.record_event(e1)
        wp.launch(D._split_searches, dim=groups << levels, inputs=[keys, origin, cell, bvh, cut, levels, groups, lcount, cap, lc, lb],
                  outputs=[lbest], device=DEV)
        wp.launch(D._gather_split, dim=groups, inputs=[groups, lcount, cap, lc, lbest], outputs=[dist, near], device=DEV)
        c2 = time.perf_counter()
        if not cpu: wp.record_event(e2)
        wp.synchronize()
        times.append(((c1 - c0) * 1e3, (c2 - c1) * 1e3) if cpu else (wp.get_event_elapsed_time(e0, e1), wp.get_event_elapsed_time(e1, e2)))
    t = np.median(np.array(times), axis=0)
    err = float(np.abs(dist.numpy()[:n] - truth).max() / field._domain.local_side)
    rows.append(dict(far_cells=K, budget=budget if budget < 2**31 - 1 else "none", levels=levels,
                     long=int(lcount.numpy()[0]), far=int(flags.sum()), searches_ms=round(float(t[0]), 4),
                     split_ms=round(float(t[1]), 4), total_ms=round(float(t.sum()), 4), max_err_side=err))
    print(rows[-1], flush=True)
