"""Probe, not part of the product (python3 bench/probes/probe_update_after_query.py MESH.npz [device]): do queries
between frames slow the frames down? `badf bench accuracy` times an update right after a million-point query and
read 4.3 ms for the bunny on an H200 where `badf bench engine` (updates back to back) read 3.0. Three sequences on
new objects, each update timed by the wall clock with the device synchronised, and the engine's own counters:
updates back to back; updates after one million-point query; an update and a 65,536-point query in turn."""
import statistics
import sys
import time

import numpy as np
import warp as wp

from badf.bench._common import deform
from badf.server.adf import DistanceField

args = [a for a in sys.argv[1:] if not a.startswith("--")]
path, device = args[0], (args[1] if len(args) > 1 else "cuda:0")
mesh = np.load(path)
vertices, faces = mesh["vertices"].astype(np.float32), mesh["faces"].astype(np.int32)
wp.init()
DistanceField(vertices, faces, device=device).update(deform(vertices, 0.5))  # compiles the kernels
lo, hi = vertices.min(axis=0), vertices.max(axis=0)
rng = np.random.default_rng(0)
big = rng.uniform(lo, hi, (1_000_000, 3)).astype(np.float32)
small = rng.uniform(lo, hi, (65_536, 3)).astype(np.float32)


def run(name, before_each=None, before_all=None, frames=12):
    field = DistanceField(vertices, faces, device=device)
    if before_all is not None:
        before_all(field)
    walls, totals, counters = [], [], []
    for k in range(1, frames + 1):
        if before_each is not None:
            before_each(field)
        wp.synchronize_device(device)
        start = time.perf_counter()
        field.update(deform(vertices, 0.02 * k))
        wp.synchronize_device(device)
        walls.append((time.perf_counter() - start) * 1e3)
        stats = field.stats()
        totals.append(stats["times_ms"]["total"])
        counters.append((stats["graph_captures"], stats["replans"], stats["measured_frames"]))
    print(f"{name}: median wall {statistics.median(walls):.2f} ms, device {statistics.median(totals):.2f}", flush=True)
    print("  walls  ", " ".join(f"{w:.2f}" for w in walls))
    print("  device ", " ".join(f"{t:.2f}" for t in totals))
    print("  (captures, replans, measured) after each:", counters)


for _ in range(2):
    run("back to back")
    run("after one 1M-point query", before_all=lambda f: f.query(big))
    run("a 65,536-point query before each", before_each=lambda f: f.query(small))
