"""Probe, not part of the product (python3 bench/probes/probe_memory.py [--meshes ...] [--depths ...] [--device cpu]
[--out FILE]): what one object holds on its device by role (`stats()["memory_bytes"]`), for shared meshes at given
depths with the defaults: after registration, after five coherent frames (a wobble of 1e-4 of the mesh's size), after
a 65,536-point ADF query and after a slice through the middle (its grid at 256 x 256). The sizes do not depend on the
device, so the CPU back-end counts what a GPU would hold. Run it on two engines (PYTHONPATH shims, as bench/ab.sh
makes) to compare them."""
import argparse
import json
import os
import sys

import numpy as np
import warp as wp

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--meshes", nargs="+", default=["stanford-bunny", "armadillo-86k"])
parser.add_argument("--depths", type=int, nargs="+", default=[7, 8])
parser.add_argument("--device", default="cpu")
parser.add_argument("--data", default=os.environ.get("BADF_SHARED_DATA", "../shared/data"))
parser.add_argument("--out")
args = parser.parse_args()

wp.config.quiet = True
from badf.server.adf import DistanceField  # noqa: E402

MIB = 2**20
rows = []
for name in args.meshes:
    mesh = np.load(os.path.join(args.data, f"{name}.npz"))
    vertices, faces = mesh["vertices"].astype(np.float64), mesh["faces"].astype(np.int64)
    size = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    for depth in args.depths:
        field = DistanceField(vertices, faces, depth=depth, device=args.device)
        row = {"mesh": name, "depth": depth, "built": field.stats()["memory_bytes"]}
        rng = np.random.default_rng(0)
        for _ in range(5):
            field.update(vertices + rng.normal(scale=1e-4 * size, size=vertices.shape))
        row["frames"] = field.stats()["memory_bytes"]
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        field.query(rng.uniform(lo, hi, size=(65536, 3)), mode="adf")
        row["query"] = field.stats()["memory_bytes"]
        field.slice("y", float((lo[1] + hi[1]) / 2), resolution=256)
        row["slice"] = field.stats()["memory_bytes"]
        row["counts"] = {k: field.stats()["counts"][k] for k in ("surface_cells", "octree_nodes", "unique_corners")}
        rows.append(row)
        line = "  ".join(f"{stage} {sum(row[stage].values()) / MIB:7.2f}" for stage in ("built", "frames", "query", "slice"))
        scratch = row["frames"]["scratch"] / 1e6
        print(f"{name:16s} d{depth}  MiB: {line}   (after frames: scratch {scratch:.2f} MB)", flush=True)
if args.out:
    with open(args.out, "w") as f:
        json.dump({"probe": "memory", "device": args.device, "engine": os.environ.get("ENGINE", ""), "rows": rows}, f,
                  indent=1)
