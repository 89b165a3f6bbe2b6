"""Probe, not part of the product (python3 bench/probes/probe_cost_order.py MESH.npz [device] [--out FILE]): the
engine's corner searches over the same corners in other orders. The engine launches them in Morton order, so a warp
of 32 neighbouring corners runs as long as its longest walk, and a walk's length grows with its corner's distance.
Ordered by distance (far first, Morton order kept within a band of distances), a warp's corners walk alike; the
question is whether that gains more than the locality it loses, before paying for a per-frame sort.
The order here comes from the engine's own answers (the host sorts them), so it is the best a seed's bound could
give. Every order's answers are checked against the engine's, corner for corner."""
import json
import sys

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search, device_times, engine_search, mesh_device_out  # noqa: E402

path, device, out = mesh_device_out()
field, inputs, count, truth = captured_search(path, device)
capacity, cell = inputs[2], float(inputs[4])
keys = inputs[0].numpy()[:count]
cells = truth / cell  # each corner's distance in finest cells
morton = np.arange(count)


def by_band(edges):
    """Far first by band of distance; Morton order within a band (a stable sort)."""
    band = np.searchsorted(np.asarray(edges, float), cells, side="right")
    return np.argsort(-band, kind="stable")


orders = {
    "morton (engine)": morton,
    "far first, bands 1,2,4,8,16 cells": by_band([1, 2, 4, 8, 16]),
    "far first, bands of 1 cell": by_band(np.arange(1, 64)),
    "far first, bands of 1/4 cell": by_band(np.arange(0.25, 64, 0.25)),
    "far first, 8+ cells only": by_band([8]),
    "near first, bands of 1 cell": by_band(np.arange(1, 64))[::-1].copy(),
}
rows = []
distance = wp.zeros(capacity, dtype=float, device=device)
nearest = wp.zeros(capacity, dtype=int, device=device)
for name, order in orders.items():
    permuted = np.zeros(capacity, np.int64)
    permuted[:count] = keys[order]
    variant = list(inputs)
    variant[0] = wp.array(permuted, dtype=wp.int64, device=device)
    launch = engine_search(variant, capacity, distance, nearest, device)
    launch()  # compile and warm
    times = []
    for _ in range(5):  # rounds of 20, so a drifting clock shows as spread
        times.append(device_times(launch, device, 20)[0])
    got = distance.numpy()[:count]
    differ = int(np.count_nonzero(got != truth[order]))
    warp_max = np.maximum.reduceat(cells[order], np.arange(0, count, 32))
    rows.append(dict(order=name, search_ms_median_of_rounds=round(float(np.median(times)), 4),
                     rounds_ms=[round(t, 4) for t in times], corners=count, differ_from_engine=differ,
                     mean_warp_longest_cells=round(float(warp_max.mean()), 3)))
    print(rows[-1], flush=True)
print(f"\n{path} depth 7, {count} corners, {wp.get_device(device).name}")
print(f"{'order':<38}{'search ms':>10}{'warp max cells':>16}{'differ':>8}")
for r in rows:
    print(f"{r['order']:<38}{r['search_ms_median_of_rounds']:>10.3f}{r['mean_warp_longest_cells']:>16.2f}"
          f"{r['differ_from_engine']:>8}")
if out:
    with open(out, "w") as f:
        json.dump(dict(mesh=path, device=wp.get_device(device).name, rows=rows), f, indent=1)
