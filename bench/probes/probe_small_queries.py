"""Probe, not part of the product: the wall time of small queries (a robot's few points a step), which the host's
work sets rather than the kernel's.

    python3 bench/probes/probe_small_queries.py MESH.npz [--device cuda:0] [--repeat K] [--json]

Prints, for 1, 16 and 256 points near the mesh, ADF and exact, the median and 90th percentile wall time of K
queries after warm-up, in three variants alternating in blocks of 20 queries in one process: "kept" (the engine:
the kernel's views kept, `KeptViews`, and its launch replayed, `KeptLaunch`), "packed" (views kept, each launch
packed anew) and "made" (views made and launch packed anew). An older engine without `KeptLaunch` runs the
first and last only.
"""

import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

from badf.server.adf import DistanceField
from badf.server.adf import _buffers
from badf.server.adf._buffers import KeptViews

KeptLaunch = getattr(_buffers, "KeptLaunch", None)
VARIANTS = {"kept": (True, True), "packed": (True, False), "made": (False, False)}
if KeptLaunch is None:
    del VARIANTS["packed"]


def use(variant):
    KeptViews.keep, launches = VARIANTS[variant]
    if KeptLaunch is not None:
        KeptLaunch.keep = launches

parser = argparse.ArgumentParser()
parser.add_argument("mesh")
parser.add_argument("--device", default="cuda:0")
parser.add_argument("--repeat", type=int, default=500)
parser.add_argument("--depth", type=int, default=7)
parser.add_argument("--json", action="store_true", help="print one JSON line instead of the table")
args = parser.parse_args()

wp.config.quiet = True
wp.init()
mesh = np.load(args.mesh)
vertices, faces = mesh["vertices"].astype(np.float32), mesh["faces"].astype(np.int32)
field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
rng = np.random.default_rng(3)
diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
rows = []
for count in (1, 16, 256):
    points = (vertices[rng.integers(0, len(vertices), count)] + rng.normal(scale=0.02 * diagonal, size=(count, 3)))
    points = points.astype(np.float32)
    for mode in ("adf", "exact"):
        for _ in range(20):
            field.query(points, mode=mode)
        walls = {variant: [] for variant in VARIANTS}
        for block in range(len(VARIANTS) * (args.repeat // 20)):
            variant = list(VARIANTS)[block % len(VARIANTS)]
            use(variant)
            for _ in range(20):
                start = time.perf_counter()
                field.query(points, mode=mode)
                walls[variant].append((time.perf_counter() - start) * 1e6)
        use("kept")
        for variant, values in walls.items():
            values.sort()
            rows.append({"points": count, "mode": mode, "views": variant,
                         "median_us": statistics.median(values), "p90_us": values[int(0.9 * len(values))]})
name = wp.get_device(args.device).name
if args.json:
    print(json.dumps({"device": name, "rows": rows}))
else:
    print(f"{name}, {time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC, {args.repeat} queries each")
    for row in rows:
        print(f"{row['points']:>5d} points {row['mode']:5s} {row['views']:6s}: median {row['median_us']:8.1f} us"
              f"  p90 {row['p90_us']:8.1f} us")
