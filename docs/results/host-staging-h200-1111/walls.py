"""Coherent update wall times of one package tree (PYTHONPATH picks it), bench-style frames, median of 200."""
import sys, time
import numpy as np
import warp as wp
wp.config.quiet = True
from badf.server.adf import DistanceField
from badf.bench._common import deform
import badf.server.adf as adf
mesh, label = sys.argv[1], sys.argv[2]
d = np.load(mesh); v = d["vertices"]; f = d["faces"]
field = DistanceField(v, f, depth=7, device="cuda:0")
frames = [deform(v, 0.02 * k) for k in range(201)]
for k in range(1, 21):
    field.update(frames[k])
walls, pre = [], []
for k in range(1, 201):
    wp.synchronize_device("cuda:0")
    t = time.perf_counter()
    field.update(frames[k])
    wp.synchronize_device("cuda:0")
    walls.append((time.perf_counter() - t) * 1e3)
s = field.stats()
print(f"{label} {mesh.split('/')[-1]}: update wall median {np.median(walls):.3f} ms (p10 {np.percentile(walls, 10):.3f}, "
      f"p90 {np.percentile(walls, 90):.3f}); last device total {s['times_ms']['total']:.3f}, upload {s['times_ms']['upload']:.3f}; "
      f"captures {s['graph_captures']} moves {s['domain_moves']} [{adf.__file__}]")
