"""Probe, not part of the product (python3 bench/probes/probe_mempool.py MESH.npz [device] [--out FILE]): does a
build wait on CUDA's allocator? Warp allocates from the device's stream-ordered memory pool, whose release
threshold CUDA sets to 0: at every synchronisation the pool hands what is free back to the driver, so each new
object's first frame (about 30 MiB for the bunny at depth 7) is allocated afresh from the driver. This builds the
same object repeatedly with the threshold at 0 and at 1 GiB, alternating in rounds, and prints the constructor's
wall time and its first frame's span by events (the README's "build" figure), medians per round."""
import json
import statistics
import sys
import time

import numpy as np
import warp as wp

from badf.server.adf import DistanceField

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import mesh_device_out, timed_constructions  # noqa: E402

path, device, out = mesh_device_out()
mesh = np.load(path)
vertices, faces = mesh["vertices"].astype(np.float32), mesh["faces"].astype(np.int32)
wp.init()
DistanceField(vertices, faces, device=device).update(vertices * 1.01)  # compiles the kernels
wp.synchronize_device(device)
print("release threshold as found:", wp.get_mempool_release_threshold(device), flush=True)

rows = []
for round_ in range(6):
    threshold = 0 if round_ % 2 == 0 else 2**30
    wp.set_mempool_release_threshold(device, threshold)
    walls, stages = timed_constructions(vertices, faces, device, 8)
    spans = [times["total"] for times in stages]
    middle = {name: round(statistics.median(s[name] for s in stages), 3) for name in stages[0]}
    rows.append(dict(round=round_, threshold=threshold, wall_ms=round(statistics.median(walls), 3),
                     span_ms=round(statistics.median(spans), 3), spans=[round(s, 3) for s in spans], stages=middle))
    print(rows[-1], flush=True)
print(f"\n{path}, {wp.get_device(device).name}, medians of 8 constructions a round")
print(f"{'round':>5}{'threshold':>12}{'wall ms':>10}{'span ms':>10}")
for r in rows:
    print(f"{r['round']:>5}{r['threshold']:>12}{r['wall_ms']:>10.2f}{r['span_ms']:>10.3f}")
if out:
    with open(out, "w") as f:
        json.dump(dict(mesh=path, device=wp.get_device(device).name, date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                       rows=rows), f, indent=1)
