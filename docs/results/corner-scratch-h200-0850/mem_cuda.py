import numpy as np, warp as wp
wp.config.quiet = True
from badf.server.adf import DistanceField
for name in ("stanford-bunny", "armadillo-86k"):
    d = np.load(f".gpudata/{name}.npz"); v = d["vertices"].astype(np.float32); v = v[0] if v.ndim == 3 else v
    f = DistanceField(v, d["faces"], depth=7, device="cuda:0")
    for k in range(1, 6): f.update(v * np.float32(1 + 0.001 * k))
    m = f.stats()["memory_bytes"]
    print(name, "cuda", {k: round(x / 1e6, 2) for k, x in m.items()}, round(sum(m.values()) / 2**20, 2), "MiB", flush=True)
