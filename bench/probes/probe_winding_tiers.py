"""Probe: the corners' winding numbers in two tiers, a loose far field first and the engine's only where it is close.

A corner's sign needs only which side of 1/2 its winding number |w| lies. The engine expands a node once the
corner is farther than WINDING_FAR_FIELD (2) node radii from its centre. A looser threshold visits fewer nodes and
errs more; where |w| comes out farther from 1/2 than a margin, that error cannot have changed the side, and only
the rest need the engine's walk. This probe counts, per threshold, the node visits (mean, and mean of each warp's
longest, for 32 corners in the engine's Morton order), how many corners fall within the margin, and how many
sides differ from the engine's threshold (with and without the second tier); on CUDA it also times the walks
(loose over every corner, then the engine's over the corners left, listed on the host for the probe).

    python bench/probes/probe_winding_tiers.py --mesh MESH.npz [MESH.npz ...] --depth 7 [--device cuda:0] [--out F.json]

On an H200 (2026-11-28 10:50, margin 0.25) the bunny's loose walk (1.25) took 0.451 ms against 1.110 for the
engine's (2); docs/results/tiers-keep-h200-1048. The engine took the two tiers (1.25, margin 0.35) from 10:40 to
12:30 that day and gave them back: on self-intersecting frames (every vertex moved by 0.08 of the diagonal) the loose
w moved from the engine's by up to 0.70 at 1.25 and 0.35 at 1.5, so the margin bounds nothing there.
"""

import argparse
import json
import time

import numpy as np
import warp as wp

from badf.server.adf import DistanceField
from badf.server.adf._bvh import BvhView, _far_field, _xyz, leaf_moments, leaf_triangle
from badf.server.adf._distance import _lattice_point
from badf.server.adf._geometry import solid_angle_checked, stack_int


@wp.kernel(enable_backward=False)
def _winding_at(keys: wp.array(dtype=wp.int64), listed: wp.array(dtype=wp.int32), count: int, origin: wp.vec3,
                cell: float, bvh: BvhView, far_field: float, w_out: wp.array(dtype=wp.float32),
                visits_out: wp.array(dtype=wp.int32)):
    k = wp.tid()
    if k >= count:
        return
    i = listed[k]
    p = _lattice_point(keys[i], origin, cell)
    total = float(0.0)
    visits = int(0)
    nodes = stack_int()
    nodes[0] = 0
    depth = int(1)
    while depth > 0:
        depth -= 1
        visits += 1
        slot = 2 * nodes[depth]
        for side in range(2):
            child = bvh.slot_child[slot + side]
            if child >= bvh.internal_count:
                a, b, c = leaf_triangle(bvh, child - bvh.internal_count)
                centre_radius, normal_area = leaf_moments(a, b, c)
                offset = _xyz(centre_radius) - p
                dist = wp.length(offset)
                if dist > far_field * centre_radius[3]:
                    total += wp.dot(_xyz(normal_area), offset / dist) / (dist * dist)
                else:
                    angle, cancelled = solid_angle_checked(p, a, b, c)
                    total += angle
            else:
                centre_radius = wp.vec4(bvh.node_moments[4 * child])
                offset = _xyz(centre_radius) - p
                dist = wp.length(offset)
                if dist > far_field * centre_radius[3]:
                    total += _far_field(bvh, child, offset / dist, dist)
                else:
                    nodes[depth] = child
                    depth += 1
    w_out[i] = total / (4.0 * wp.pi)
    visits_out[i] = visits


def _walk(field, listed: np.ndarray, far_field: float, w, visits, repeat: int) -> float:
    """Run the walk over the listed corners; the median of `repeat` device times (ms; 0 on the CPU)."""
    o, device = field._octree, field._device
    cell = field._domain.local_side / (1 << field._depth)
    ids = wp.array(listed.astype(np.int32), dtype=wp.int32, device=device)
    times = []
    for _ in range(repeat if device.is_cuda else 1):
        if device.is_cuda:
            begin, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
            wp.record_event(begin)
        wp.launch(_winding_at, dim=len(listed), inputs=[o.corner_keys, ids, len(listed), field._domain.origin,
                  cell, field._bvh.view(), far_field], outputs=[w, visits], device=device)
        if device.is_cuda:
            wp.record_event(end)
            wp.synchronize_device(device)
            times.append(wp.get_event_elapsed_time(begin, end))
    return float(np.median(times)) if times else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mesh", nargs="+", required=True)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--device", default=None)
    parser.add_argument("--thresholds", type=float, nargs="+", default=[1.5, 1.25, 1.0, 0.75])
    parser.add_argument("--margin", type=float, default=0.35)
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    wp.config.quiet = True
    report = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "depth": args.depth,
              "margin": args.margin, "meshes": {}}
    for path in args.mesh:
        data = np.load(path)
        v = data["vertices"]
        v = (v[0] if v.ndim == 3 else v).astype(np.float32)
        field = DistanceField(v, data["faces"], depth=args.depth, sign="winding", device=args.device)
        device = field._device
        report["device"] = wp.get_device(device).name if device.is_cuda else "cpu"
        n = field._octree.corner_count
        every = np.arange(n, dtype=np.int32)
        w = wp.zeros(n, dtype=wp.float32, device=device)
        visits = wp.zeros(n, dtype=wp.int32, device=device)

        def run(threshold, listed, repeat):
            ms = _walk(field, listed, threshold, w, visits, repeat)
            return ms, w.numpy().copy(), visits.numpy().copy()

        def warp_longest(vis):
            pad = (-len(vis)) % 32
            return float(np.pad(vis, (0, pad)).reshape(-1, 32).max(axis=1).mean())

        base_ms, base_w, base_v = run(2.0, every, args.repeat)
        base_side = np.abs(base_w) > 0.5
        rows = [{"threshold": 2.0, "ms": base_ms, "visits": float(base_v.mean()), "warp_longest": warp_longest(base_v),
                 "near_half": int(np.sum(np.abs(np.abs(base_w) - 0.5) <= args.margin))}]
        for threshold in args.thresholds:
            ms, loose_w, loose_v = run(threshold, every, args.repeat)
            close = np.abs(np.abs(loose_w) - 0.5) <= args.margin
            redo = every[close]
            redo_ms = run(2.0, redo, args.repeat)[0] if len(redo) else 0.0
            two_tier = np.where(close, base_side, np.abs(loose_w) > 0.5)
            rows.append({"threshold": threshold, "ms": ms, "redo_ms": redo_ms, "visits": float(loose_v.mean()),
                         "warp_longest": warp_longest(loose_v), "redone": int(close.sum()),
                         "largest_change": float(np.max(np.abs(loose_w - base_w))),
                         "sides_differ_loose": int(np.sum((np.abs(loose_w) > 0.5) != base_side)),
                         "sides_differ_two_tier": int(np.sum(two_tier != base_side))})
        name = path.rsplit("/", 1)[-1].removesuffix(".npz")
        report["meshes"][name] = {"corners": n, "rows": rows}
        print(f"{name}: {n} corners, depth {args.depth}, margin {args.margin}, {report['device']}")
        print("  threshold  ms      redo_ms  visits  warp_longest  redone   largest|dw|  differ(loose)  differ(2 tiers)")
        for r in rows:
            print(f"  {r['threshold']:9.2f}  {r['ms']:6.3f}  {r.get('redo_ms', 0.0):7.3f}  {r['visits']:6.1f}  "
                  f"{r['warp_longest']:12.1f}  {r.get('redone', 0):6d}  {r.get('largest_change', 0.0):11.3g}  "
                  f"{r.get('sides_differ_loose', 0):13d}  {r.get('sides_differ_two_tier', 0):15d}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
