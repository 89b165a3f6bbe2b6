"""Probe, not part of the product (python3 bench/probes/probe_slabs.py MESH.npz [device] [--out FILE]): the corner
searches with a slab beside each 4-wide node's box.

The searches' kernel lasts as long as its far corners' walks (probe_binned_near: the bunny's 14% farthest corners
alone take 0.81 of the 1.00 ms of every corner's walks on an H200). A corner d away from a smooth surface meets it
in a ball that the surface only touches, but the boxes of the small triangles around the touching point reach into
that ball over a disc of radius about sqrt(d s) for triangles of size s, so the walk opens every node there. A slab
(the node's mean normal n, and the least and greatest n.x over its triangles) is much thinner than the box for a
patch of a smooth surface, and the distance from p to it is a second lower bound for every triangle under the node.
Here each node's slab is made from its own entries: the vertices of the single triangles among them and the corners
of the boxes of the nodes among them (which hold every triangle below them), so the slab holds every triangle under
the node; a node with no triangle of its own among its entries keeps its box alone. A walk that pops a node whose
slab lies farther than the best so far passes over it.

Measured: node visits per corner (mean, the mean over warps of 32 of their longest, the longest) with and without the
slabs, and on a GPU the search kernel's time over the engine's own corners and seeds (last frame's faces), every
answer checked against the engine's, corner for corner.
"""
import json
import sys

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import SEEDING_INPUTS, captured_search, device_times, engine_search, mesh_device_out  # noqa: E402

from badf.server.adf import _distance  # noqa: E402
from badf.server.adf._bvh import (NO_CHILD, BvhView, beats, entry_distances_sq, leaf_distance_sq,  # noqa: E402
                                  leaf_triangle, load_vec4, wide_stack_float, wide_stack_int)
from badf.server.adf._distance import EXACT_ROUNDING, _corner_seed, _held_to_band, _lattice_point  # noqa: E402

# a slab's faces are moved out by this much of the largest |n.x| or node size, so that rounding never puts a
# triangle outside its slab
SLAB_PAD = 1e-5


@wp.func
def _take(n: wp.vec3, x: wp.vec3, lo: float, hi: float, size: float):
    s = wp.dot(n, x)
    return wp.min(lo, s), wp.max(hi, s), wp.max(size, wp.abs(s))


@wp.kernel(enable_backward=False, module="unique", module_options=EXACT_ROUNDING)
def _make_slabs(bvh: BvhView, capacity: int, slab: wp.array(dtype=wp.vec4), slab_hi: wp.array(dtype=wp.float32)):
    k = wp.tid()
    n = wp.vec3()
    own = int(0)
    for j in range(4):
        child = bvh.wide_child[4 * k + j]
        if child < 0:
            a, b, c = leaf_triangle(bvh, -1 - child)
            n += wp.cross(b - a, c - a)
            own += 1
    length = wp.length(n)
    if own == 0 or length <= 0.0:
        slab[k] = wp.vec4(0.0, 0.0, 0.0, -1.0e30)  # no slab: the box alone
        slab_hi[k] = 1.0e30
        return
    n = n / length
    lo = float(1.0e30)
    hi = float(-1.0e30)
    size = float(0.0)
    for j in range(4):
        child = bvh.wide_child[4 * k + j]
        if child == NO_CHILD:
            continue
        if child < 0:
            a, b, c = leaf_triangle(bvh, -1 - child)
            lo, hi, size = _take(n, a, lo, hi, size)
            lo, hi, size = _take(n, b, lo, hi, size)
            lo, hi, size = _take(n, c, lo, hi, size)
        else:
            # the child's box, from this node's planes (entry j)
            lower = wp.vec3(load_vec4(bvh.wide_planes, 6 * k)[j], load_vec4(bvh.wide_planes, 6 * k + 1)[j],
                            load_vec4(bvh.wide_planes, 6 * k + 2)[j])
            upper = wp.vec3(load_vec4(bvh.wide_planes, 6 * k + 3)[j], load_vec4(bvh.wide_planes, 6 * k + 4)[j],
                            load_vec4(bvh.wide_planes, 6 * k + 5)[j])
            for corner in range(8):
                x = wp.vec3(wp.where((corner & 1) != 0, upper[0], lower[0]),
                            wp.where((corner & 2) != 0, upper[1], lower[1]),
                            wp.where((corner & 4) != 0, upper[2], lower[2]))
                lo, hi, size = _take(n, x, lo, hi, size)
            size = wp.max(size, wp.length(upper - lower))
    pad = SLAB_PAD * size + 1.0e-30
    slab[k] = wp.vec4(n[0], n[1], n[2], lo - pad)
    slab_hi[k] = hi + pad


def _walk(use_slabs: bool, max_registers: int | None = None):
    def nearest_counted(bvh: BvhView, p: wp.vec3, best_leaf: int, best_sq: float, slab: wp.array(dtype=wp.vec4),
                        slab_hi: wp.array(dtype=wp.float32)):
        """The engine's corner walk (`_wide_searches` without the tie pass), counting visits, with slabs or not."""
        nodes = wide_stack_int()
        bounds = wide_stack_float()
        nodes[0] = 0
        bounds[0] = 0.0
        top = int(1)
        visits = int(0)
        passed = int(0)
        while top > 0:
            top -= 1
            if bounds[top] > best_sq:
                continue
            node = nodes[top]
            if wp.static(use_slabs):
                s = slab[node]
                along = s[0] * p[0] + s[1] * p[1] + s[2] * p[2]
                gap = wp.max(wp.max(s[3] - along, along - slab_hi[node]), 0.0)
                if gap * gap > best_sq:
                    passed += 1
                    continue
            visits += 1
            d = entry_distances_sq(bvh, p, node)
            child = wp.vec4i()
            for j in range(4):
                child[j] = bvh.wide_child[4 * node + j]
            for j in range(4):
                if child[j] < 0 and d[j] <= best_sq:
                    leaf = -1 - child[j]
                    d_sq = leaf_distance_sq(bvh, leaf, p)
                    if beats(d_sq, leaf, best_sq, best_leaf):
                        best_sq = d_sq
                        best_leaf = leaf
            for j in range(4):
                if child[j] >= 0 and child[j] != NO_CHILD:
                    if not d[j] <= best_sq:
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
        return best_leaf, best_sq, visits, passed

    nearest_counted.__name__ = nearest_counted.__qualname__ = "nearest_counted" + ("_slabs" if use_slabs else "")
    nearest_counted = wp.func(nearest_counted, module="unique")

    def searches(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int,
                 origin: wp.vec3, cell: float, inv_side: float, depth: int, bvh: BvhView, band: float, coherent: int,
                 previous_keys: wp.array(dtype=wp.int32), previous_face: wp.array(dtype=wp.int32),
                 previous_count: wp.array(dtype=wp.int32), previous_capacity: int,
                 previous_lattice: wp.array(dtype=wp.vec4), slab: wp.array(dtype=wp.vec4),
                 slab_hi: wp.array(dtype=wp.float32), distance: wp.array(dtype=wp.float32),
                 nearest: wp.array(dtype=wp.int32), visits: wp.array(dtype=wp.int32),
                 passed: wp.array(dtype=wp.int32)):
        i = wp.tid()
        if i >= wp.min(count[0], capacity):
            return
        p = _lattice_point(corner_keys[i], origin, cell)
        seed = _corner_seed(bvh, p, origin, inv_side, depth, coherent, previous_keys, previous_face, previous_count,
                            previous_capacity, previous_lattice)
        best, best_sq = _held_to_band(seed, leaf_distance_sq(bvh, seed, p), band)
        best, best_sq, v, s = nearest_counted(bvh, p, best, best_sq, slab, slab_hi)
        distance[i] = wp.sqrt(best_sq)
        nearest[i] = best
        visits[i] = v
        passed[i] = s

    searches.__name__ = searches.__qualname__ = ("slab_searches" if use_slabs else "counted_searches") + (
        f"_cap{max_registers}" if max_registers else "")
    return wp.kernel(searches, enable_backward=False, module="unique", module_options=EXACT_ROUNDING,
                     cuda_max_registers=max_registers)


def main():
    path, device, out = mesh_device_out()
    field, inputs, count, truth = captured_search(path, device)
    assert len(inputs) == SEEDING_INPUTS
    capacity, bvh, cell = inputs[2], inputs[7], float(inputs[4])
    truth_leaf = field._corners.leaf.numpy()[:count].copy()
    name = wp.get_device(device).name
    wide = field._bvh.wide.capacity
    slab = wp.zeros(wide, dtype=wp.vec4, device=device)
    slab_hi = wp.zeros(wide, dtype=wp.float32, device=device)

    def make_slabs():
        wp.launch(_make_slabs, dim=wide, inputs=[bvh, wide], outputs=[slab, slab_hi], device=device)

    make_slabs()
    distance = wp.zeros(capacity, dtype=float, device=device)
    nearest = wp.zeros(capacity, dtype=int, device=device)
    visits = wp.zeros(capacity, dtype=int, device=device)
    passed = wp.zeros(capacity, dtype=int, device=device)
    engine = engine_search(inputs, capacity, distance, nearest, device)
    engine()
    rows = []
    if device != "cpu":
        rows.append(dict(walk="engine's kernel", ms=round(float(np.median(
            [device_times(engine, device, 10)[0] for _ in range(3)])), 4)))
    rows.append(dict(walk="slabs made (one thread per 4-wide node)", ms=round(float(np.median(
        [device_times(make_slabs, device, 10)[0] for _ in range(3)])), 4)))
    far = truth >= 8 * cell
    for use_slabs in (False, True):
        kernel = _walk(use_slabs)

        def launch():
            wp.launch(kernel, dim=capacity, inputs=[*inputs, slab, slab_hi],
                      outputs=[distance, nearest, visits, passed], device=device, block_dim=_distance.SEARCH_BLOCK_DIM)

        distance.fill_(-1.0)
        launch()
        got, got_leaf = distance.numpy()[:count], nearest.numpy()[:count]
        v = visits.numpy()[:count]
        warps = np.maximum.reduceat(v, np.arange(0, count, 32))
        row = dict(walk="with slabs" if use_slabs else "boxes alone (counted)",
                   ms=round(float(np.median([device_times(launch, device, 10 if device != "cpu" else 2)[0]
                                             for _ in range(3)])), 4),
                   visits_mean=round(float(v.mean()), 2), visits_far_mean=round(float(v[far].mean()), 2),
                   far_corners=int(far.sum()), warp_longest_mean=round(float(warps.mean()), 2),
                   visits_max=int(v.max()), slab_passes_mean=round(float(passed.numpy()[:count].mean()), 2),
                   distances_differ=int(np.count_nonzero(got != truth)),
                   leaves_differ=int(np.count_nonzero(got_leaf != truth_leaf)))
        rows.append(row)
        print(row, flush=True)
    print(f"\n{path}: depth 7, {count} corners ({int(far.sum())} at 8 cells or more), {name}")
    print(f"{'walk':<42}{'ms':>8}{'visits':>8}{'far':>8}{'warp max':>10}{'max':>6}{'passed':>8}{'differ':>8}")
    for r in rows:
        print(f"{r['walk']:<42}{r['ms']:>8.3f}{r.get('visits_mean', float('nan')):>8.1f}"
              f"{r.get('visits_far_mean', float('nan')):>8.1f}{r.get('warp_longest_mean', float('nan')):>10.1f}"
              f"{r.get('visits_max', 0):>6}{r.get('slab_passes_mean', float('nan')):>8.1f}"
              f"{r.get('distances_differ', 0) + r.get('leaves_differ', 0):>8}")
    if out:
        with open(out, "w") as f:
            json.dump(dict(mesh=path, device=name, corners=count, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
