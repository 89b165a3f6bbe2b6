"""Probe: query times near a mesh, uniform in its domain, and 1e8 of its sizes away.

From far enough every face lies at the same float32 distance, so a search that visits every box as near
as the best so far visits every face. This times exact and ADF queries of three point sets and prints
each with the sum of its distances (the same sums before and after a change say the answers agree).

    python bench/probes/probe_far_queries.py --mesh stanford-bunny.npz --device cuda:0 --out far.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", required=True, help=".npz with vertices (N, 3) and faces (M, 3)")
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--points", type=int, default=1_000_000, help="points near and uniform (far: 1/50 of it)")
    parser.add_argument("--out", default=None, help="JSON file to write")
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    from badf.server.adf import DistanceField

    data = np.load(args.mesh)
    vertices, faces = data["vertices"], data["faces"]
    field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
    side = field.info()["domain"]["side"]
    centre = np.asarray(field.info()["domain"]["centre"])
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(max(args.points // 50, 1), 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    point_sets = {
        "uniform": (centre + (rng.random((args.points, 3)) - 0.5) * side).astype(np.float32),
        "near": np.asarray(vertices[rng.integers(0, len(vertices), args.points)] * 1.01, np.float32),
        "far (1e8 sizes)": (centre + directions * side * 1e8).astype(np.float32),
    }
    out = {"device": args.device, "mesh": args.mesh, "depth": args.depth, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    for name, points in point_sets.items():
        for mode in ("exact", "adf"):
            field.query(points[:1000], mode=mode)
            wp.synchronize()
            times = []
            for _ in range(5 if name != "far (1e8 sizes)" else 1):
                start = time.perf_counter()
                result = field.query(points, mode=mode)
                times.append(time.perf_counter() - start)
            ms = 1e3 * float(np.median(times))
            total = float(np.sum(result.distance.astype(np.float64)))
            out[f"{name} {mode}"] = {"points": len(points), "ms": round(ms, 3), "sum_of_distances": total}
            print(f"{name:16s} {mode:5s} {len(points):9d} points {ms:9.2f} ms  (sum of distances {total:.9e})", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
