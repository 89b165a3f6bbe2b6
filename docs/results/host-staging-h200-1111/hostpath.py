"""The update's host work before the device's, as main did it and as the tree does it, on 200 distinct frames."""
import time, sys
import numpy as np
import warp as wp
wp.config.quiet = True
from badf.server.adf._inputs import as_vertices, check_bounds
from badf.server.adf._field import bounds
mesh = sys.argv[1] if len(sys.argv) > 1 else ".gpudata/stanford-bunny.npz"
v = np.load(mesh)["vertices"].astype(np.float32)
frames = [(v * np.float32(1 + 1e-4 * k)).astype(np.float32) for k in range(200)]
pinned = wp.empty(len(v), dtype=wp.vec3, device="cpu", pinned=wp.is_cuda_available())
def old(a):
    a = as_vertices(a, expected_count=len(v)); lo, hi = bounds(a); pinned.numpy()[:] = a
def new(a):
    a = as_vertices(a, expected_count=len(v), check_finite=False); h = pinned.numpy(); h[:] = a
    lo, hi = bounds(h); check_bounds(lo, hi, a, "vertices")
res = {"old": [], "new": []}
for rep in range(6):
    for name, fn in (("old", old), ("new", new)) if rep % 2 == 0 else (("new", new), ("old", old)):
        t = time.perf_counter()
        for a in frames: fn(a)
        res[name].append((time.perf_counter() - t) * 1e3 / len(frames))
for name, ts in res.items():
    print(f"host work before the device, {name}: median {np.median(ts):.4f} ms per frame (runs {', '.join(f'{x:.4f}' for x in ts)})")
