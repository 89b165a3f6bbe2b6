import json, statistics, sys, time
import numpy as np, warp as wp
wp.config.quiet = True
from badf.server.adf import DistanceField
rows = []
for name in ("stanford-bunny", "armadillo-86k"):
    d = np.load(f"/work/shared/data/{name}.npz")
    v, f = d["vertices"].astype(np.float32), d["faces"]
    field = DistanceField(v, f, depth=6, device="cpu")
    rng = np.random.default_rng(4)
    lo, hi = v.min(axis=0), v.max(axis=0)
    for n in (64, 128, 256, 512, 1024, 2047):
        pts = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
        field.query(pts, mode="exact")
        reps = max(5, int(3000 / n))
        ts = []
        for _ in range(reps):
            s = time.perf_counter(); r = field.query(pts, mode="exact"); ts.append((time.perf_counter() - s) * 1e3)
        rows.append({"mesh": name, "points": n, "ms": statistics.median(ts), "checksum": float(np.sum(r.distance.astype(np.float64)))})
print(json.dumps(rows))
