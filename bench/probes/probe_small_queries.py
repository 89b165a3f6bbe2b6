"""Probe, not part of the product: the wall time of small queries (a robot's few points a step), which the host's
work sets rather than the kernel's.

    python3 bench/probes/probe_small_queries.py MESH.npz [--device cuda:0] [--repeat K] [--json]

Prints, for 1, 16 and 256 points near the mesh, ADF and exact, the median and 90th percentile wall time of K
queries after warm-up, and the revision of the engine imported (run it once per revision, alternating, to compare
them on one machine).
"""

import argparse
import json
import pathlib
import statistics
import time

import numpy as np
import warp as wp

import badf.server.adf as adf
from badf.server.adf import DistanceField

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
        walls = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            field.query(points, mode=mode)
            walls.append((time.perf_counter() - start) * 1e6)
        walls.sort()
        rows.append({"points": count, "mode": mode, "median_us": statistics.median(walls),
                     "p90_us": walls[int(0.9 * len(walls))]})
where = str(pathlib.Path(adf.__file__).resolve().parent.parent.parent)
if args.json:
    print(json.dumps({"engine": where, "device": wp.get_device(args.device).name, "rows": rows}))
else:
    print(f"engine at {where}, {wp.get_device(args.device).name}, median of {args.repeat}")
    for row in rows:
        print(f"{row['points']:>5d} points {row['mode']:5s} median {row['median_us']:8.1f} us  p90 {row['p90_us']:8.1f} us")
