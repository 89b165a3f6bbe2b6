"""Probe, not part of the product (python3 bench/probes/probe_bricks.py MESH.npz [device] [repeats]): corner
searches shared by the corners of a brick (2x2x2, 2x2x1 or 2x1x1 lattice points, consecutive in Morton order),
one thread walking the BVH once for all of them, against the engine's own kernel, one thread per corner.

A brick's walk opens a node when its box comes within the largest of the brick's bounds of the box around the
brick's corners (that distance is never more than any one corner's, so every box a corner's own walk opens is
opened too) and tests each triangle it reaches against every corner, keeping each corner's least (distance,
leaf) as `beats` orders them. The answers are then the engine's; the probe counts any that differ.

It ran on the H100 at aa2a613 (docs/results/bricks-h100-0123), when the engine's corner searches walked the
binary tree; since 92e1c93 they walk its 4-wide view, which the bricks here do not. It reads the binary
tree's boxes, which the engine no longer keeps (dropped after 2f9483c): check out 2f9483c to run it."""
import sys

import numpy as np
import warp as wp

from badf.server.adf import _distance as D
from badf.server.adf._bvh import (_INV_FOUR_PI, LEAF_SIZE, BvhView, _far_field, _xyz, beats, leaf_moments,
                                  leaf_triangle)
from badf.server.adf._sign import WOUND_CANCELLED, WOUND_INSIDE, WOUND_OUTSIDE, wound_side
from badf.server.adf._geometry import (box_distance_sq, load_vec4, solid_angle_checked, stack_float, stack_int,
                                       triangle_distance_sq)

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search, device_times, engine_search  # noqa: E402


@wp.func
def _box_box_sq(lo: wp.vec3, hi: wp.vec3, lower: wp.vec4, upper: wp.vec4) -> float:
    d = wp.max(wp.max(wp.vec3(lower[0], lower[1], lower[2]) - hi, lo - wp.vec3(upper[0], upper[1], upper[2])),
               wp.vec3(0.0))
    return wp.dot(d, d)


@wp.kernel(enable_backward=False)
def brick_heads(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int, bits: int,
                head: wp.array(dtype=wp.int32)):
    i = wp.tid()
    flag = 0
    if i < wp.min(count[0], capacity):
        if i == 0 or (corner_keys[i] >> wp.int64(bits)) != (corner_keys[i - 1] >> wp.int64(bits)):
            flag = 1
    head[i] = flag


@wp.kernel(enable_backward=False)
def brick_list(head: wp.array(dtype=wp.int32), rank: wp.array(dtype=wp.int32), capacity: int,
               first: wp.array(dtype=wp.int32), brick_count: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if head[i] != 0:
        first[rank[i]] = i
    if i == capacity - 1:
        brick_count[0] = rank[i] + head[i]


def make_brick_kernel(bits: int, tight: bool, registers: int):
    size = 1 << bits
    vec_f = wp.types.vector(length=size, dtype=wp.float32)
    vec_i = wp.types.vector(length=size, dtype=wp.int32)

    def brick_searches(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int,
                       origin: wp.vec3, cell: float, inv_side: float, depth: int, bvh: BvhView, band: float,
                       coherent: int, previous_keys: wp.array(dtype=wp.int64),
                       previous_face: wp.array(dtype=wp.int32), previous_count: wp.array(dtype=wp.int32),
                       previous_capacity: int, previous_origin: wp.vec3, previous_inv_cell: float,
                       brick_first: wp.array(dtype=wp.int32), brick_count: wp.array(dtype=wp.int32),
                       distance: wp.array(dtype=wp.float32), nearest: wp.array(dtype=wp.int32)):
        brick = wp.tid()
        if brick >= brick_count[0]:
            return
        n = wp.min(count[0], capacity)
        first = brick_first[brick]
        group = corner_keys[first] >> wp.int64(bits)
        xs = vec_f()
        ys = vec_f()
        zs = vec_f()
        best_sq = vec_f()
        best = vec_i()
        seeds = vec_i()
        members = int(0)
        lo = wp.vec3(1.0e30)
        hi = wp.vec3(-1.0e30)
        for k in range(wp.static(size)):
            i = first + k
            j = first
            if i < n:
                if (corner_keys[i] >> wp.int64(bits)) == group:
                    j = i
                    members = k + 1
            p = D._lattice_point(corner_keys[j], origin, cell)
            seed = D._corner_seed(bvh, p, origin, inv_side, depth, coherent, previous_keys, previous_face,
                                  previous_count, previous_capacity, previous_origin, previous_inv_cell)
            leaf, leaf_sq = D._seed_bound(bvh, p, seed, band)
            xs[k] = p[0]
            ys[k] = p[1]
            zs[k] = p[2]
            best_sq[k] = leaf_sq
            best[k] = leaf
            seeds[k] = seed
            lo = wp.min(lo, p)
            hi = wp.max(hi, p)
        bound = float(0.0)
        for k in range(wp.static(size)):
            bound = wp.max(bound, best_sq[k])
        if bvh.internal_count > 0:
            nodes = stack_int()
            bounds = stack_float()
            nodes[0] = 0
            bounds[0] = 0.0
            top = int(1)
            while top > 0:
                top -= 1
                if bounds[top] > bound:
                    continue
                slot = 2 * nodes[top]
                lower_n = load_vec4(bvh.slot_lower, slot)
                upper_n = load_vec4(bvh.slot_upper, slot)
                lower_f = load_vec4(bvh.slot_lower, slot + 1)
                upper_f = load_vec4(bvh.slot_upper, slot + 1)
                d_n = _box_box_sq(lo, hi, lower_n, upper_n)
                d_f = _box_box_sq(lo, hi, lower_f, upper_f)
                near = slot
                far = slot + 1
                if d_f < d_n:  # the nearer child first
                    near = slot + 1
                    far = slot
                    swap_lower = lower_n
                    lower_n = lower_f
                    lower_f = swap_lower
                    swap_upper = upper_n
                    upper_n = upper_f
                    upper_f = swap_upper
                    swap_d = d_n
                    d_n = d_f
                    d_f = swap_d
                # small children (a triangle) first, the nearer one first, then the larger ones pushed far first
                for side in range(2):
                    lower = lower_n
                    upper = upper_n
                    d = d_n
                    child = near
                    if side == 1:
                        lower = lower_f
                        upper = upper_f
                        d = d_f
                        child = far
                    if lower[3] <= float(LEAF_SIZE) and d <= bound:
                        leaf = bvh.slot_first[child]
                        a, b, c = leaf_triangle(bvh, leaf)
                        bound = float(0.0)
                        for k in range(wp.static(size)):
                            q = wp.vec3(xs[k], ys[k], zs[k])
                            test = True
                            if wp.static(tight):
                                test = box_distance_sq(q, wp.vec3(lower[0], lower[1], lower[2]),
                                                       wp.vec3(upper[0], upper[1], upper[2])) <= best_sq[k]
                            if test:
                                d_sq = triangle_distance_sq(q, a, b, c)
                                if beats(d_sq, leaf, best_sq[k], best[k]):
                                    best_sq[k] = d_sq
                                    best[k] = leaf
                            bound = wp.max(bound, best_sq[k])
                if lower_f[3] > float(LEAF_SIZE) and d_f <= bound:
                    nodes[top] = bvh.slot_child[far]
                    bounds[top] = d_f
                    top += 1
                if lower_n[3] > float(LEAF_SIZE) and d_n <= bound:
                    nodes[top] = bvh.slot_child[near]
                    bounds[top] = d_n
                    top += 1
        else:
            a, b, c = leaf_triangle(bvh, 0)
            for k in range(wp.static(size)):
                d_sq = triangle_distance_sq(wp.vec3(xs[k], ys[k], zs[k]), a, b, c)
                if beats(d_sq, 0, best_sq[k], best[k]):
                    best_sq[k] = d_sq
                    best[k] = 0
        for k in range(wp.static(size)):
            if k < members:
                D._write_answer(first + k, best[k], best_sq[k], seeds[k], band, distance, nearest)

    return wp.kernel(brick_searches, name=f"bricks_{bits}_{int(tight)}_{registers}", enable_backward=False,
                     module="unique", cuda_max_registers=registers,
                     module_options=D.EXACT_ROUNDING)


def make_brick_winding(bits: int, registers: int):
    """The corners' winding numbers, one walk per brick: each stack entry carries the mask of the brick's corners
    for which its node is near, so every corner adds the same terms in the same order as its own walk would."""
    size = 1 << bits
    vec_f = wp.types.vector(length=size, dtype=wp.float32)

    def brick_winding(corner_keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), capacity: int,
                      origin: wp.vec3, cell: float, bvh: BvhView, brick_first: wp.array(dtype=wp.int32),
                      brick_count: wp.array(dtype=wp.int32), inside: wp.array(dtype=wp.uint8)):
        brick = wp.tid()
        if brick >= brick_count[0]:
            return
        n = wp.min(count[0], capacity)
        first = brick_first[brick]
        group = corner_keys[first] >> wp.int64(bits)
        xs = vec_f()
        ys = vec_f()
        zs = vec_f()
        total = vec_f()
        members = int(0)
        for k in range(wp.static(size)):
            i = first + k
            j = first
            if i < n:
                if (corner_keys[i] >> wp.int64(bits)) == group:
                    j = i
                    members = k + 1
            p = D._lattice_point(corner_keys[j], origin, cell)
            xs[k] = p[0]
            ys[k] = p[1]
            zs[k] = p[2]
        if bvh.internal_count == 0:
            for k in range(wp.static(size)):
                if k < members:
                    inside[first + k] = wound_side(bvh, wp.vec3(xs[k], ys[k], zs[k]))
            return
        cancelled = int(0)
        nodes = stack_int()
        masks = stack_int()
        nodes[0] = 0
        masks[0] = (1 << members) - 1
        top = int(1)
        while top > 0:
            top -= 1
            slot = 2 * nodes[top]
            mask = masks[top]
            for side in range(2):
                child = bvh.slot_child[slot + side]
                if child >= bvh.internal_count:
                    leaf = child - bvh.internal_count
                    a, b, c = leaf_triangle(bvh, leaf)
                    centre_radius, normal_area = leaf_moments(a, b, c)
                    for k in range(wp.static(size)):
                        if (mask >> k) & 1 != 0:
                            p = wp.vec3(xs[k], ys[k], zs[k])
                            offset = _xyz(centre_radius) - p
                            dist = wp.length(offset)
                            if dist > bvh.far_field * centre_radius[3]:
                                total[k] = total[k] + wp.dot(_xyz(normal_area), offset / dist) / (dist * dist)
                            else:
                                angle, near_cancelled = solid_angle_checked(p, a, b, c)
                                total[k] = total[k] + angle
                                if near_cancelled:
                                    cancelled = cancelled | (1 << k)
                else:
                    centre_radius = load_vec4(bvh.node_moments, 4 * child)
                    near = int(0)
                    for k in range(wp.static(size)):
                        if (mask >> k) & 1 != 0:
                            offset = _xyz(centre_radius) - wp.vec3(xs[k], ys[k], zs[k])
                            dist = wp.length(offset)
                            if dist > bvh.far_field * centre_radius[3]:
                                total[k] = total[k] + _far_field(bvh, child, offset / dist, dist)
                            else:
                                near = near | (1 << k)
                    if near != 0:
                        nodes[top] = child
                        masks[top] = near
                        top += 1
        for k in range(wp.static(size)):
            if k < members:
                side_k = WOUND_OUTSIDE
                if (cancelled >> k) & 1 != 0:
                    side_k = WOUND_CANCELLED
                elif wp.abs(total[k] * _INV_FOUR_PI) > 0.5:
                    side_k = WOUND_INSIDE
                inside[first + k] = side_k

    return wp.kernel(brick_winding, name=f"brick_winding_{bits}_{registers}", enable_backward=False,
                     module="unique", cuda_max_registers=registers)


def main():
    path = sys.argv[1]
    device = sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
    repeats = int(sys.argv[3]) if len(sys.argv) > 3 else 10
    field, inputs, n, truth = captured_search(path, device)
    capacity = inputs[2]
    engine_near = field._corners.leaf.numpy()[:n].copy()
    cuda = device != "cpu"
    z = lambda dtype: wp.zeros(capacity, dtype=dtype, device=device)  # noqa: E731
    distance, nearest, head, rank, first = z(float), z(int), z(int), z(int), z(int)
    bricks = wp.zeros(1, dtype=int, device=device)

    def timed(launches):
        return device_times(launches, device, repeats)

    engine = engine_search(inputs, capacity, distance, nearest, device)

    side_stream = wp.Stream(device) if cuda else None
    inside = wp.zeros(capacity, dtype=wp.uint8, device=device)
    wind_inputs = [inputs[0], inputs[1], capacity, inputs[3], inputs[4], inputs[7]]

    def engine_winding():
        wp.launch(D.winding_kernel(), dim=capacity, inputs=wind_inputs, outputs=[inside], device=device,
                  block_dim=D.SIGN_BLOCK_DIM)

    def list_bricks(bits):
        wp.launch(brick_heads, dim=capacity, inputs=[inputs[0], inputs[1], capacity, bits], outputs=[head],
                  device=device)
        wp.utils.array_scan(head, rank, inclusive=False)
        wp.launch(brick_list, dim=capacity, inputs=[head, rank, capacity], outputs=[first, bricks], device=device)

    def together(search, winding):
        """The searches and the winding numbers side by side on two streams, as the engine runs them."""
        def run():
            if side_stream is None:
                search()
                winding()
                return
            main = wp.get_stream(device)
            side_stream.wait_stream(main)
            with wp.ScopedStream(side_stream, sync_enter=False):
                winding()
            search()
            main.wait_stream(side_stream)
        return run

    engine_winding()
    wp.synchronize()
    engine_inside = inside.numpy()[:n].copy()
    cases = [("search: engine, one thread per corner", None, engine, "search")]
    for bits in (3, 2):
        for tight in (False, True):
            for registers in (64, 128):
                kernel = make_brick_kernel(bits, tight, registers)

                def bricked(kernel=kernel, bits=bits):
                    list_bricks(bits)
                    wp.launch(kernel, dim=capacity, inputs=inputs + [first, bricks], outputs=[distance, nearest],
                              device=device, block_dim=D.SEARCH_BLOCK_DIM)

                cases.append((f"search: bricks of {1 << bits}, {'per-corner box' if tight else 'brick box'}, "
                              f"{registers} reg", bits, bricked, "search"))
    cases.append(("winding: engine, one thread per corner", None, engine_winding, "winding"))
    for bits in (3, 2):
        for registers in (48, 64, 128):
            kernel = make_brick_winding(bits, registers)

            def wound(kernel=kernel, bits=bits):
                list_bricks(bits)
                wp.launch(kernel, dim=capacity, inputs=wind_inputs + [first, bricks], outputs=[inside], device=device,
                          block_dim=D.SIGN_BLOCK_DIM)

            cases.append((f"winding: bricks of {1 << bits}, {registers} reg", bits, wound, "winding"))
    cases.append(("both: engine", None, together(engine, engine_winding), "both"))
    search_8 = make_brick_kernel(3, False, 128)
    winding_8 = make_brick_winding(3, 64)

    def both_bricks():
        list_bricks(3)
        main = wp.get_stream(device) if cuda else None
        if main is not None:
            side_stream.wait_stream(main)
            with wp.ScopedStream(side_stream, sync_enter=False):
                wp.launch(winding_8, dim=capacity, inputs=wind_inputs + [first, bricks], outputs=[inside],
                          device=device, block_dim=D.SIGN_BLOCK_DIM)
        else:
            wp.launch(winding_8, dim=capacity, inputs=wind_inputs + [first, bricks], outputs=[inside], device=device)
        wp.launch(search_8, dim=capacity, inputs=inputs + [first, bricks], outputs=[distance, nearest], device=device,
                  block_dim=D.SEARCH_BLOCK_DIM)
        if main is not None:
            main.wait_stream(side_stream)

    cases.append(("both: bricks of 8 (search 128 reg, winding 64 reg)", 3, both_bricks, "both"))
    rows = []
    for round_ in range(2):  # two rounds, alternating, so drift shows
        for name, bits, launches, kind in cases:
            distance.zero_()
            nearest.zero_()
            inside.zero_()
            launches()  # compile and warm
            median, best = timed(launches)
            d, leaf, side = distance.numpy()[:n], nearest.numpy()[:n], inside.numpy()[:n]
            row = dict(round=round_, case=name, median_ms=round(median, 4), min_ms=round(best, 4),
                       threads=int(bricks.numpy()[0]) if bits else n,
                       distance_diff=int(np.count_nonzero(d != truth)) if kind != "winding" else -1,
                       leaf_diff=int(np.count_nonzero(leaf != engine_near)) if kind != "winding" else -1,
                       side_diff=int(np.count_nonzero(side != engine_inside)) if kind != "search" else -1)
            rows.append(row)
            print(row, flush=True)
    print(f"\n{path}, {n} corners, {wp.get_device(device).name}; -1: not compared")
    print(f"{'case':<58} {'round':>5} {'median ms':>10} {'min ms':>8} {'threads':>8} {'d diff':>7} {'leaf diff':>9} "
          f"{'side diff':>9}")
    for r in rows:
        print(f"{r['case']:<58} {r['round']:>5} {r['median_ms']:>10.4f} {r['min_ms']:>8.4f} {r['threads']:>8} "
              f"{r['distance_diff']:>7} {r['leaf_diff']:>9} {r['side_diff']:>9}")


if __name__ == "__main__":
    main()
