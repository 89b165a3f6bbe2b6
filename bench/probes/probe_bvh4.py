"""Probe, not part of the product (python3 bench/probes/probe_bvh4.py MESH.npz [device] [repeats]): the corner
searches over a 4-wide BVH, against the engine's own kernel over its binary one.

The 4-wide tree is the engine's binary tree with every other level folded away (collapsed on the host from the
refitted tree): a node's children are its binary node's grandchildren, or a child itself where that is a single
triangle. A visit reads four boxes (128 bytes) where the binary walk reads two (64), and a walk takes about half
the steps, each of which waits on the load before it. The search keeps the engine's order of answers (`beats`:
the least distance, then the least leaf), so its answers are the engine's; the probe counts any that differ.

It ran on the H100 at 9ab8bc3 (docs/results/bvh4-h100-0129). Since 92e1c93 the engine's corner searches walk
the planes variant themselves (`nearest_leaf_wide` over `WideTree`), so its "binary (engine)" rows now time
that walk; check out 9ab8bc3 to compare with the binary one. It reads the binary tree's boxes, which the engine
no longer keeps (dropped after 2f9483c): check out 2f9483c to run it."""
import sys
import time

import numpy as np
import warp as wp

from badf.server.adf import _distance as D
from badf.server.adf._bvh import BvhView, beats, leaf_distance_sq
from badf.server.adf._geometry import box_distance_sq, load_vec4, stack_float, stack_int

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search, device_times, engine_search  # noqa: E402

EMPTY = 3.0e38  # an absent child's box: lower above upper, so no point comes within reach of it


def collapse(bvh) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(lower (4m, 4) float32, upper (4m, 4), child (4m,) int32, m) of the 4-wide tree: child >= 0 is a node,
    -1 - leaf a triangle; lower's w is 1 for a triangle, 2 for a node, 0 for no child."""
    lower_2, upper_2 = bvh.slot_lower.numpy(), bvh.slot_upper.numpy()
    child_2, first_2 = bvh.slot_child.numpy(), bvh.slot_first.numpy()
    count_2 = lower_2[:, 3]
    entries_lower, entries_upper, entries_child = [], [], []
    index = {0: 0}  # binary node -> 4-wide node
    order = [0]
    k = 0
    while k < len(order):
        node = order[k]
        k += 1
        slots = []
        for slot in (2 * node, 2 * node + 1):
            if count_2[slot] <= 1:
                slots.append(slot)
            else:
                inner = child_2[slot]
                slots.extend((2 * inner, 2 * inner + 1))
        row_lower = np.full((4, 4), EMPTY, np.float32)
        row_upper = np.full((4, 4), -EMPTY, np.float32)
        row_child = np.full(4, -1, np.int32)
        row_lower[:, 3] = 0.0
        for j, slot in enumerate(slots):
            row_lower[j, :3], row_upper[j, :3] = lower_2[slot, :3], upper_2[slot, :3]
            if count_2[slot] <= 1:
                row_lower[j, 3] = 1.0
                row_child[j] = -1 - first_2[slot]
            else:
                row_lower[j, 3] = 2.0
                inner = int(child_2[slot])
                index[inner] = len(order)
                order.append(inner)
                row_child[j] = index[inner]
        entries_lower.append(row_lower)
        entries_upper.append(row_upper)
        entries_child.append(row_child)
    return (np.concatenate(entries_lower), np.concatenate(entries_upper), np.concatenate(entries_child),
            len(order))


@wp.func
def _xyz(v: wp.vec4) -> wp.vec3:
    return wp.vec3(v[0], v[1], v[2])


@wp.func
def nearest_bvh4(bvh: BvhView, lower: wp.array(dtype=wp.vec4), upper: wp.array(dtype=wp.vec4),
                 child: wp.array(dtype=wp.int32), p: wp.vec3, best_leaf: int, best_sq: float):
    nodes = stack_int()
    bounds = stack_float()
    nodes[0] = 0
    bounds[0] = 0.0
    top = int(1)
    while top > 0:
        top -= 1
        if bounds[top] > best_sq:
            continue
        base = 4 * nodes[top]
        d = wp.vec4()
        kind = wp.vec4()
        for j in range(4):
            lo = load_vec4(lower, base + j)
            d[j] = box_distance_sq(p, _xyz(lo), _xyz(load_vec4(upper, base + j)))
            kind[j] = lo[3]
        # triangles first, then the nodes pushed farthest first, so the nearest is walked next
        for j in range(4):
            if kind[j] == 1.0 and d[j] <= best_sq:
                leaf = -1 - child[base + j]
                d_sq = leaf_distance_sq(bvh, leaf, p)
                if beats(d_sq, leaf, best_sq, best_leaf):
                    best_sq = d_sq
                    best_leaf = leaf
        for step in range(4):
            far = int(-1)
            far_d = float(-1.0)
            for j in range(4):
                if kind[j] == 2.0 and d[j] <= best_sq and d[j] > far_d:
                    far = j
                    far_d = d[j]
            if far >= 0:
                nodes[top] = child[base + far]
                bounds[top] = far_d
                top += 1
                kind[far] = 0.0
    return best_leaf, best_sq


ABSENT = 2**31 - 1


def to_soa(lower_4: np.ndarray, upper_4: np.ndarray, child_4: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(planes (6m, 4): x, y, z of the four lower corners then of the four upper ones; child (4m,), ABSENT for
    none) of the 4-wide tree, so a visit reads its four boxes in six 16-byte loads."""
    m = len(child_4) // 4
    lo = lower_4.reshape(m, 4, 4)[:, :, :3]
    hi = upper_4.reshape(m, 4, 4)[:, :, :3]
    planes = np.concatenate([lo.transpose(0, 2, 1), hi.transpose(0, 2, 1)], axis=1)  # (m, 6, 4)
    child = np.where(lower_4[:, 3] == 0.0, ABSENT, child_4).astype(np.int32)
    return np.ascontiguousarray(planes.reshape(6 * m, 4), dtype=np.float32), child


@wp.func
def _axis_gap(p: float, lo: wp.vec4, hi: wp.vec4) -> wp.vec4:
    return wp.vec4(wp.max(wp.max(lo[0] - p, p - hi[0]), 0.0), wp.max(wp.max(lo[1] - p, p - hi[1]), 0.0),
                   wp.max(wp.max(lo[2] - p, p - hi[2]), 0.0), wp.max(wp.max(lo[3] - p, p - hi[3]), 0.0))


@wp.func
def nearest_bvh4_soa(bvh: BvhView, planes: wp.array(dtype=wp.vec4), child: wp.array(dtype=wp.int32), p: wp.vec3,
                     best_leaf: int, best_sq: float):
    nodes = stack_int()
    bounds = stack_float()
    nodes[0] = 0
    bounds[0] = 0.0
    top = int(1)
    while top > 0:
        top -= 1
        if bounds[top] > best_sq:
            continue
        node = nodes[top]
        gx = _axis_gap(p[0], load_vec4(planes, 6 * node), load_vec4(planes, 6 * node + 3))
        gy = _axis_gap(p[1], load_vec4(planes, 6 * node + 1), load_vec4(planes, 6 * node + 4))
        gz = _axis_gap(p[2], load_vec4(planes, 6 * node + 2), load_vec4(planes, 6 * node + 5))
        # the same sum, in the same order, as box_distance_sq's dot product
        d = wp.vec4()
        for j in range(4):
            d[j] = gx[j] * gx[j] + gy[j] * gy[j] + gz[j] * gz[j]
        c = wp.vec4i()
        for j in range(4):
            c[j] = child[4 * node + j]
        for j in range(4):
            if c[j] < 0 and d[j] <= best_sq:
                leaf = -1 - c[j]
                d_sq = leaf_distance_sq(bvh, leaf, p)
                if beats(d_sq, leaf, best_sq, best_leaf):
                    best_sq = d_sq
                    best_leaf = leaf
        for step in range(4):
            far = int(-1)
            far_d = float(-1.0)
            for j in range(4):
                if c[j] >= 0 and c[j] != ABSENT and d[j] <= best_sq and d[j] > far_d:
                    far = j
                    far_d = d[j]
            if far >= 0:
                nodes[top] = c[far]
                bounds[top] = far_d
                top += 1
                c[far] = ABSENT
    return best_leaf, best_sq


@wp.kernel(enable_backward=False, module="unique", cuda_max_registers=D.SEARCH_MAX_REGISTERS,
           module_options=D.EXACT_ROUNDING)
def corner_searches_bvh4_soa(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int,
                             origin: wp.vec3, cell: float, inv_side: float, depth: int, bvh: BvhView, band: float,
                             coherent: int, previous_keys: wp.array(dtype=wp.int64),
                             previous_face: wp.array(dtype=wp.int32), previous_count: wp.array(dtype=wp.int32),
                             previous_capacity: int, previous_origin: wp.vec3, previous_inv_cell: float,
                             planes: wp.array(dtype=wp.vec4), child: wp.array(dtype=wp.int32),
                             distance: wp.array(dtype=wp.float32), nearest: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if i >= wp.min(count[0], capacity):
        return
    p = D._lattice_point(corner_keys[i], origin, cell)
    seed = D._corner_seed(bvh, p, origin, inv_side, depth, coherent, previous_keys, previous_face, previous_count,
                          previous_capacity, previous_origin, previous_inv_cell)
    best, best_sq = D._seed_bound(bvh, p, seed, band)
    best, best_sq = nearest_bvh4_soa(bvh, planes, child, p, best, best_sq)
    D._write_answer(i, best, best_sq, seed, band, distance, nearest)


@wp.kernel(enable_backward=False, module="unique", cuda_max_registers=D.SEARCH_MAX_REGISTERS,
           module_options=D.EXACT_ROUNDING)
def corner_searches_bvh4(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int,
                         origin: wp.vec3, cell: float, inv_side: float, depth: int, bvh: BvhView, band: float,
                         coherent: int, previous_keys: wp.array(dtype=wp.int64),
                         previous_face: wp.array(dtype=wp.int32), previous_count: wp.array(dtype=wp.int32),
                         previous_capacity: int, previous_origin: wp.vec3, previous_inv_cell: float,
                         lower: wp.array(dtype=wp.vec4), upper: wp.array(dtype=wp.vec4),
                         child: wp.array(dtype=wp.int32), distance: wp.array(dtype=wp.float32),
                         nearest: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if i >= wp.min(count[0], capacity):
        return
    p = D._lattice_point(corner_keys[i], origin, cell)
    seed = D._corner_seed(bvh, p, origin, inv_side, depth, coherent, previous_keys, previous_face, previous_count,
                          previous_capacity, previous_origin, previous_inv_cell)
    best, best_sq = D._seed_bound(bvh, p, seed, band)
    best, best_sq = nearest_bvh4(bvh, lower, upper, child, p, best, best_sq)
    D._write_answer(i, best, best_sq, seed, band, distance, nearest)


def main():
    path = sys.argv[1]
    device = sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
    repeats = int(sys.argv[3]) if len(sys.argv) > 3 else 10
    field, inputs, n, truth = captured_search(path, device)
    capacity = inputs[2]
    engine_near = field._corners.leaf.numpy()[:n].copy()
    t0 = time.perf_counter()
    lower_4, upper_4, child_4, nodes_4 = collapse(field._bvh)
    collapse_ms = (time.perf_counter() - t0) * 1e3
    lower = wp.array(lower_4, dtype=wp.vec4, device=device)
    upper = wp.array(upper_4, dtype=wp.vec4, device=device)
    child = wp.array(child_4, dtype=wp.int32, device=device)
    planes_4, child_soa = to_soa(lower_4, upper_4, child_4)
    planes = wp.array(planes_4, dtype=wp.vec4, device=device)
    child_s = wp.array(child_soa, dtype=wp.int32, device=device)
    distance = wp.zeros(capacity, dtype=float, device=device)
    nearest = wp.zeros(capacity, dtype=int, device=device)

    def timed(launches):
        return device_times(launches, device, repeats)

    engine = engine_search(inputs, capacity, distance, nearest, device)

    def wide():
        wp.launch(corner_searches_bvh4, dim=capacity, inputs=inputs + [lower, upper, child],
                  outputs=[distance, nearest], device=device, block_dim=D.SEARCH_BLOCK_DIM)

    def wide_soa():
        wp.launch(corner_searches_bvh4_soa, dim=capacity, inputs=inputs + [planes, child_s],
                  outputs=[distance, nearest], device=device, block_dim=D.SEARCH_BLOCK_DIM)

    rows = []
    for round_ in range(3):
        for name, launch in (("binary (engine)", engine), ("4-wide", wide), ("4-wide, planes", wide_soa)):
            distance.zero_()
            nearest.zero_()
            launch()
            median, least = timed(launch)
            d, leaf = distance.numpy()[:n], nearest.numpy()[:n]
            rows.append((name, round_, median, least, int(np.count_nonzero(d != truth)),
                         int(np.count_nonzero(leaf != engine_near))))
    print(f"\n{path}, {n} corners, {wp.get_device(device).name}; 4-wide nodes {nodes_4} (binary {field._bvh.internal_count}),"
          f" collapsed on the host in {collapse_ms:.0f} ms")
    print(f"{'tree':<16} {'round':>5} {'median ms':>10} {'min ms':>8} {'d diff':>7} {'leaf diff':>9}")
    for name, round_, median, least, d_diff, leaf_diff in rows:
        print(f"{name:<16} {round_:>5} {median:>10.4f} {least:>8.4f} {d_diff:>7} {leaf_diff:>9}")


if __name__ == "__main__":
    main()
