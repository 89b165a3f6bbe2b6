"""Probe, not part of the product (python3 bench/probes/probe_shape_builder.py MESH.npz [MESH.npz ...] [--repeat N]):
the SAH shape's host time (`_bvh_shape.sah_shape`, the Warp kernel on the CPU back-end) with one thread and with the
CPU back-end's threads, best and median of N after one that compiles it, and whether the two trees are the same."""
import statistics
import sys
import time

import numpy as np
import warp as wp

from badf.server.adf._bvh_shape import sah_shape
from badf.server.adf._threads import cpu_threads

paths = [a for a in sys.argv[1:] if a.endswith(".npz")]
repeat = int(sys.argv[sys.argv.index("--repeat") + 1]) if "--repeat" in sys.argv else 7
wp.init()
threads = cpu_threads()
print(f"cpu threads: {threads}")
for path in paths:
    mesh = np.load(path)
    vertices = mesh["vertices"][0] if mesh["vertices"].ndim == 3 else mesh["vertices"]
    faces = mesh["faces"]
    shapes, times = {}, {}
    for count in (1, threads):
        shapes[count] = sah_shape(vertices, faces, threads=count)
        walls = []
        for _ in range(repeat):
            started = time.perf_counter()
            sah_shape(vertices, faces, threads=count)
            walls.append((time.perf_counter() - started) * 1e3)
        times[count] = walls
    same = all(np.array_equal(a, b) for a, b in zip(shapes[1], shapes[threads]))
    print(f"{path} ({len(faces)} triangles, depth {shapes[1].depth}): " + "; ".join(
        f"{count} thread(s) best {min(w):.1f} ms, median {statistics.median(w):.1f}" for count, w in times.items())
        + f"; same tree: {same}", flush=True)
