"""Probe, not part of the product (python3 bench/probes/probe_binned_near.py MESH.npz [device] [--out FILE]): the
corners near the surface answered from bins of triangles instead of a BVH walk each.

The engine walks the BVH once per corner. On a GPU those walks are bound by latency and divergence: a warp of 32
corners runs as long as its longest walk, and even a walk that starts from the exact nearest face visits about 40
nodes and tests about 29 triangles to prove it nearest (engine.md, "Where the time goes at depth 7"). Here the
lattice is cut into bins of 2^b finest cells a side, which are Morton prefixes of the corners' keys, and each
triangle is listed in every bin that its bounding box, grown by a reach R, overlaps. A corner then tests every
triangle of its bin's list, and those lists are the same for the 2^(3b) corners of a bin, which are neighbours in
the engine's (Morton) order: a warp loads the same triangles, walks nothing, and waits on no dependent loads. Any
triangle within R of a corner has its grown box around the corner, so a corner whose nearest listed triangle lies
within R has its exact nearest (the same least (distance, leaf) as the walk, by the same `beats`); the others are
left to the engine's search, from the same seeds.

The question is what that costs on a GPU against the walks, per mesh, bin size and reach: listing and sorting the
pairs each frame, the tests (a corner tests every triangle listed for its bin: 76 to 370 on the bunny at depth 7,
against 29 for a walk), and the corners left over. Every answer is checked against the engine's, corner for corner.
"""
import json
import sys

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search, device_times, engine_search, mesh_device_out  # noqa: E402

from badf.server.adf import _distance  # noqa: E402
from badf.server.adf._bvh import BvhView, beats, leaf_distance_sq, leaf_triangle  # noqa: E402
from badf.server.adf._distance import EXACT_ROUNDING, _lattice_point  # noqa: E402
from badf.server.adf._geometry import morton3  # noqa: E402

# (bin bits b, reach in finest cells): a corner of a cell the surface crosses lies within sqrt(3) cells of it, one
# of the halo's within 2 sqrt(3)
SETTINGS = [(1, 1.8), (1, 2.5), (1, 3.5), (2, 2.5), (2, 3.5)]
# the grown boxes are grown a little more than R, so that rounding in the bins' bounds never leaves out a triangle
# that a corner finds within R
GROWTH = 1.0 + 1e-3


@wp.kernel(enable_backward=False)
def _count_bins(bvh: BvhView, origin: wp.vec3, inv_bin: float, grow: float, last_bin: int,
                counts: wp.array(dtype=wp.int32)):
    leaf = wp.tid()
    a, b, c = leaf_triangle(bvh, leaf)
    lo = (wp.min(wp.min(a, b), c) - wp.vec3(grow) - origin) * inv_bin
    hi = (wp.max(wp.max(a, b), c) + wp.vec3(grow) - origin) * inv_bin
    n = int(1)
    for k in range(3):
        first = wp.clamp(int(wp.floor(lo[k])), 0, last_bin)
        last = wp.clamp(int(wp.floor(hi[k])), 0, last_bin)
        n *= last - first + 1
    counts[leaf] = n


@wp.kernel(enable_backward=False)
def _list_bins(bvh: BvhView, origin: wp.vec3, inv_bin: float, grow: float, last_bin: int,
               offsets: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int64), leaves: wp.array(dtype=wp.int32)):
    leaf = wp.tid()
    a, b, c = leaf_triangle(bvh, leaf)
    lo = (wp.min(wp.min(a, b), c) - wp.vec3(grow) - origin) * inv_bin
    hi = (wp.max(wp.max(a, b), c) + wp.vec3(grow) - origin) * inv_bin
    x0 = wp.clamp(int(wp.floor(lo[0])), 0, last_bin)
    y0 = wp.clamp(int(wp.floor(lo[1])), 0, last_bin)
    z0 = wp.clamp(int(wp.floor(lo[2])), 0, last_bin)
    x1 = wp.clamp(int(wp.floor(hi[0])), 0, last_bin)
    y1 = wp.clamp(int(wp.floor(hi[1])), 0, last_bin)
    z1 = wp.clamp(int(wp.floor(hi[2])), 0, last_bin)
    slot = offsets[leaf]
    for x in range(x0, x1 + 1):
        for y in range(y0, y1 + 1):
            for z in range(z0, z1 + 1):
                keys[slot] = morton3(x, y, z)
                leaves[slot] = leaf
                slot += 1


@wp.kernel(enable_backward=False, module="unique", module_options=EXACT_ROUNDING)  # as the engine's searches
def _answer_near(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int,
                 origin: wp.vec3, cell: float, bvh: BvhView, bin_keys: wp.array(dtype=wp.int64),
                 bin_leaves: wp.array(dtype=wp.int32), listed: int, bits: int, reach_sq: float,
                 distance: wp.array(dtype=wp.float32), nearest: wp.array(dtype=wp.int32),
                 left_count: wp.array(dtype=wp.int32), left_keys: wp.array(dtype=wp.int64),
                 left_corner: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if i >= wp.min(count[0], capacity):
        return
    key = corner_keys[i]
    p = _lattice_point(key, origin, cell)
    wanted = key >> wp.int64(3 * bits)  # the corner's bin: a prefix of its Morton key
    lo = int(0)
    hi = listed
    while lo < hi:
        mid = (lo + hi) // 2
        if bin_keys[mid] < wanted:
            lo = mid + 1
        else:
            hi = mid
    best = int(-1)
    best_sq = reach_sq
    j = lo
    while j < listed:
        if bin_keys[j] != wanted:
            break
        leaf = bin_leaves[j]
        d_sq = leaf_distance_sq(bvh, leaf, p)
        if beats(d_sq, leaf, best_sq, best):
            best_sq = d_sq
            best = leaf
        j += 1
    if best >= 0:
        distance[i] = wp.sqrt(best_sq)
        nearest[i] = best
    else:
        slot = wp.atomic_add(left_count, 0, 1)
        left_keys[slot] = key
        left_corner[slot] = i


@wp.kernel(enable_backward=False)
def _write_back(left_count: wp.array(dtype=wp.int32), left_corner: wp.array(dtype=wp.int32),
                left_distance: wp.array(dtype=wp.float32), left_nearest: wp.array(dtype=wp.int32),
                distance: wp.array(dtype=wp.float32), nearest: wp.array(dtype=wp.int32)):
    k = wp.tid()
    if k >= left_count[0]:
        return
    distance[left_corner[k]] = left_distance[k]
    nearest[left_corner[k]] = left_nearest[k]


def main():
    path, device, out = mesh_device_out()
    field, inputs, count, truth = captured_search(path, device)
    corner_keys, count_array, capacity, origin, cell = inputs[0], inputs[1], inputs[2], inputs[3], float(inputs[4])
    bvh = inputs[7]
    depth = int(inputs[6])
    leaves = field._bvh.face_count
    truth_leaf = field._corners.leaf.numpy()[:count].copy()
    name = wp.get_device(device).name
    print(f"{path}: {leaves} triangles, depth {depth}, {count} corners, {name}", flush=True)

    distance = wp.zeros(capacity, dtype=float, device=device)
    nearest = wp.zeros(capacity, dtype=int, device=device)
    walk_all = engine_search(inputs, capacity, distance, nearest, device)
    walk_all()
    walk_ms = [device_times(walk_all, device, 10)[0] for _ in range(3)]
    row_walk = dict(method="engine walk, every corner", ms=round(float(np.median(walk_ms)), 4))
    print(row_walk, flush=True)

    winding_inside = wp.zeros(capacity, dtype=wp.uint8, device=device)

    def winding():
        wp.launch(_distance.winding_kernel(), dim=capacity,
                  inputs=[corner_keys, count_array, capacity, origin, cell, bvh], outputs=[winding_inside],
                  device=device, block_dim=_distance.SIGN_BLOCK_DIM)

    winding()
    row_winding = dict(method="winding numbers alone (for meshes they sign)",
                       ms=round(float(np.median([device_times(winding, device, 10)[0] for _ in range(3)])), 4))
    print(row_winding, flush=True)
    side = wp.Stream(device) if device != "cpu" else None

    def beside_winding(searches):
        """The searches with the winding numbers on a stream beside them, as the engine runs them."""
        if side is None:
            return lambda: (searches(), winding())

        def run():
            main_stream = wp.get_stream(device)
            side.wait_stream(main_stream)
            with wp.ScopedStream(side):
                winding()
            searches()
            main_stream.wait_stream(side)
        return run

    walk_beside = beside_winding(walk_all)
    walk_beside()
    row_walk["ms_beside_winding"] = round(float(np.median([device_times(walk_beside, device, 10)[0]
                                                          for _ in range(3)])), 4)
    rows = [row_walk, row_winding]

    counts = wp.zeros(leaves, dtype=wp.int32, device=device)
    offsets = wp.zeros(leaves, dtype=wp.int32, device=device)
    left_count = wp.zeros(1, dtype=wp.int32, device=device)
    left_keys = wp.zeros(capacity, dtype=wp.int64, device=device)
    left_corner = wp.zeros(capacity, dtype=wp.int32, device=device)
    left_distance = wp.zeros(capacity, dtype=float, device=device)
    left_nearest = wp.zeros(capacity, dtype=int, device=device)
    left_inputs = list(inputs)
    left_inputs[0], left_inputs[1] = left_keys, left_count
    walk_left = engine_search(left_inputs, capacity, left_distance, left_nearest, device)
    for bits, reach_cells in SETTINGS:
        bin_side = cell * (1 << bits)
        grow = reach_cells * cell * GROWTH
        last_bin = (1 << (depth - bits))  # lattice points run 0 .. 2^depth, so bins 0 .. 2^(depth - b)
        bin_inputs = [bvh, origin, 1.0 / bin_side, grow, last_bin]
        wp.launch(_count_bins, dim=leaves, inputs=bin_inputs, outputs=[counts], device=device)
        wp.utils.array_scan(counts, offsets, inclusive=False)
        listed = int(offsets.numpy()[-1] + counts.numpy()[-1])  # an engine would plan this size
        bin_keys = wp.zeros(2 * listed, dtype=wp.int64, device=device)
        bin_leaves = wp.zeros(2 * listed, dtype=wp.int32, device=device)
        reach_sq = float((reach_cells * cell) ** 2)

        def list_bins():
            wp.launch(_count_bins, dim=leaves, inputs=bin_inputs, outputs=[counts], device=device)
            wp.utils.array_scan(counts, offsets, inclusive=False)
            wp.launch(_list_bins, dim=leaves, inputs=[*bin_inputs, offsets], outputs=[bin_keys, bin_leaves],
                      device=device)
            wp.utils.radix_sort_pairs(bin_keys, bin_leaves, listed)

        def answer_near():
            left_count.zero_()
            wp.launch(_answer_near, dim=capacity,
                      inputs=[corner_keys, count_array, capacity, origin, cell, bvh, bin_keys, bin_leaves, listed,
                              bits, reach_sq],
                      outputs=[distance, nearest, left_count, left_keys, left_corner], device=device,
                      block_dim=_distance.SEARCH_BLOCK_DIM)

        def answer_left():
            walk_left()
            wp.launch(_write_back, dim=capacity,
                      inputs=[left_count, left_corner, left_distance, left_nearest], outputs=[distance, nearest],
                      device=device)

        def all_of_it():
            list_bins()
            answer_near()
            answer_left()

        distance.fill_(-1.0)
        all_of_it()
        got, got_leaf = distance.numpy()[:count], nearest.numpy()[:count]
        left = int(left_count.numpy()[0])
        per_corner = np.diff(np.searchsorted(bin_keys.numpy()[:listed],
                                             np.stack([corner_keys.numpy()[:count] >> (3 * bits),
                                                       (corner_keys.numpy()[:count] >> (3 * bits)) + 1])), axis=0)[0]
        timed = {}
        for label, fn in [("list_bins", list_bins), ("answer_near", answer_near), ("answer_left", answer_left),
                          ("all", all_of_it), ("all_beside_winding", beside_winding(all_of_it))]:
            fn()
            timed[label] = round(float(np.median([device_times(fn, device, 10)[0] for _ in range(3)])), 4)
        row = dict(method=f"bins of {1 << bits} cells, reach {reach_cells} cells", bits=bits, reach_cells=reach_cells,
                   pairs=listed, tests_per_corner_mean=round(float(per_corner.mean()), 1),
                   tests_per_corner_max=int(per_corner.max()), corners_left=left,
                   corners_left_fraction=round(left / count, 4),
                   distances_differ=int(np.count_nonzero(got != truth)),
                   distance_largest_difference_cells=float(np.max(np.abs(got - truth)) / cell),
                   leaves_differ=int(np.count_nonzero(got_leaf != truth_leaf)), ms=timed["all"], stages_ms=timed,
                   ms_beside_winding=timed["all_beside_winding"])
        rows.append(row)
        print(row, flush=True)

    print(f"\n{path}: {leaves} triangles, depth {depth}, {count} corners, {name} (device ms, median of 3 rounds "
          f"of 10)")
    print(f"{'method':<34}{'ms':>8}{'+winding':>10}{'list':>8}{'near':>8}{'left':>8}{'left %':>8}{'tests':>8}"
          f"{'differ':>8}")
    for r in rows:
        s = r.get("stages_ms", {})
        print(f"{r['method']:<34}{r['ms']:>8.3f}{r.get('ms_beside_winding', float('nan')):>10.3f}"
              f"{s.get('list_bins', float('nan')):>8.3f}{s.get('answer_near', float('nan')):>8.3f}"
              f"{s.get('answer_left', float('nan')):>8.3f}{100 * r.get('corners_left_fraction', float('nan')):>8.1f}"
              f"{r.get('tests_per_corner_mean', float('nan')):>8.0f}"
              f"{r.get('distances_differ', 0) + r.get('leaves_differ', 0):>8}")
    if out:
        with open(out, "w") as f:
            json.dump(dict(mesh=path, device=name, depth=depth, corners=count, triangles=leaves, rows=rows), f,
                      indent=1)


if __name__ == "__main__":
    main()
