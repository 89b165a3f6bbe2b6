"""Probe, not part of the product (run by hand on a GPU: python3 bench/probes/probe_searches.py MESH.npz [device]):
per-thread clock and SM of the corner searches on one coherent update. Results: docs/results/probe-searches-*."""
import json
import sys

import numpy as np
import warp as wp

from badf.server.adf import _distance as D
from badf.server.adf._bvh import BvhView, spatial_seed

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search  # noqa: E402

@wp.func_native("""
#if defined(__CUDA_ARCH__)
return (wp::int64)clock64();
#else
return 0;
#endif
""")
def clock() -> wp.int64: ...

@wp.func_native("""
#if defined(__CUDA_ARCH__)
unsigned int r; asm volatile("mov.u32 %0, %%smid;" : "=r"(r)); return (int)r;
#else
return 0;
#endif
""")
def smid() -> int: ...

@wp.func_native("""
#if defined(__CUDA_ARCH__)
unsigned long long t; asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t)); return (wp::int64)t;
#else
return 0;
#endif
""")
def gtimer() -> wp.int64: ...

@wp.kernel(enable_backward=False)
def probe(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int, origin: wp.vec3,
          cell: float, inv_side: float, depth: int, bvh: BvhView, band: float, coherent: int,
          previous_keys: wp.array(dtype=wp.int64), previous_face: wp.array(dtype=wp.int32),
          previous_count: wp.array(dtype=wp.int32), previous_capacity: int, previous_origin: wp.vec3,
          previous_inv_cell: float, budget: int,
          t_start: wp.array(dtype=wp.int64), t_end: wp.array(dtype=wp.int64), sm: wp.array(dtype=int),
          out_d: wp.array(dtype=float), order: wp.array(dtype=int), use_order: int):
    i = wp.tid()
    if i >= wp.min(count[0], capacity):
        return
    if use_order != 0:
        i = order[i]
    t0 = gtimer()
    p = D._lattice_point(corner_keys[i], origin, cell)
    seed = int(-1)
    if coherent != 0:
        seed = D.coherent_seed(bvh, p, depth, previous_keys, previous_face, previous_count, previous_capacity,
                               previous_origin, previous_inv_cell)
    else:
        seed = spatial_seed(bvh, p, origin, inv_side)
    best_leaf, best_sq, finished = D._nearest_with_band_budgeted(bvh, p, seed, band, budget)
    out_d[i] = wp.sqrt(best_sq)
    t_end[i] = gtimer()
    t_start[i] = t0
    sm[i] = smid()

DEV = sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
field, inputs, n, _ = captured_search(sys.argv[1], DEV)
inputs = inputs + [D.UNLIMITED_VISITS]
cap = inputs[2]
t0 = wp.zeros(cap, dtype=wp.int64, device=DEV); t1 = wp.zeros(cap, dtype=wp.int64, device=DEV)
sm = wp.zeros(cap, dtype=int, device=DEV); od = wp.zeros(cap, dtype=float, device=DEV)
report = {"corners": n}
order = wp.zeros(cap, dtype=int, device=DEV)
for block, use_order in ((128, 0), (32, 0), (128, 1)):
    if use_order:
        cells = od.numpy()[:n] / inputs[4]
        bucket = np.floor(np.log2(np.maximum(cells, 0.5))).astype(int)
        order.assign(np.concatenate([np.argsort(-bucket, kind="stable"), np.arange(n, cap)]).astype(np.int32))
    for rep in range(3):
        wp.synchronize()
        if DEV != "cpu":
            e0 = wp.Event(enable_timing=True); e1 = wp.Event(enable_timing=True)
            wp.record_event(e0)
        wp.launch(probe, dim=cap, inputs=inputs, outputs=[t0, t1, sm, od, order, int(use_order)], block_dim=block, device=DEV)
        if DEV != "cpu":
            wp.record_event(e1)
        wp.synchronize()
    ms = wp.get_event_elapsed_time(e0, e1) if DEV != "cpu" else 0.0
    s, e, m = t0.numpy()[:n], t1.numpy()[:n], sm.numpy()[:n]
    dur = (e - s) / 1e3  # us
    span = (e.max() - s.min()) / 1e3
    per_sm_end = np.array([e[m == k].max() - s.min() for k in np.unique(m)]) / 1e3
    per_sm_busy = np.array([ (e[m == k].max() - s[m == k].min()) for k in np.unique(m)]) / 1e3
    slowest = np.argsort(dur)[::-1]
    start_rel = (s - s.min()) / 1e3
    report[f"block{block}" + ("_far_first" if use_order else "")] = dict(event_ms=round(ms, 4), span_us=round(span, 1),
        thread_us_mean=round(dur.mean(), 1), p50=round(np.median(dur), 1), p99=round(np.percentile(dur, 99), 1), max=round(dur.max(), 1),
        longest_start_us=[round(x, 1) for x in start_rel[slowest[:5]]], longest_dur_us=[round(x, 1) for x in dur[slowest[:5]]],
        longest_dist_cells=[round(float(od.numpy()[j]) / inputs[4], 1) for j in slowest[:5]],
        sm_end_us_min_med_max=[round(per_sm_end.min(), 1), round(np.median(per_sm_end), 1), round(per_sm_end.max(), 1)],
        sm_busy_us_min_med_max=[round(per_sm_busy.min(), 1), round(np.median(per_sm_busy), 1), round(per_sm_busy.max(), 1)],
        last_start_us=round(start_rel.max(), 1),
        dur_by_dist={f"{lo}-{hi}": round(float(dur[(od.numpy()[:n] / inputs[4] >= lo) & (od.numpy()[:n] / inputs[4] < hi)].mean()), 1)
                     for lo, hi in ((0, 1), (1, 2), (2, 4), (4, 8), (8, 16), (16, 10**9))})
print(json.dumps(report, indent=1))
