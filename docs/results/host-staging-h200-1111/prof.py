"""Host profile of coherent updates on CUDA: where the wall time beyond the device's goes."""
import cProfile, pstats, sys, time, io
import numpy as np
import warp as wp
wp.config.quiet = True
from badf.server.adf import DistanceField
from badf.bench._common import deform
mesh = sys.argv[1] if len(sys.argv) > 1 else ".gpudata/stanford-bunny.npz"
d = np.load(mesh); v = d["vertices"].astype(np.float32); f = d["faces"]
field = DistanceField(v, f, depth=7, device="cuda:0")
frames = [deform(v, 0.5 + 0.002 * k).astype(np.float32) for k in range(260)]
for k in range(30):
    field.update(frames[k])
wp.synchronize()
t = time.perf_counter()
for k in range(30, 130):
    field.update(frames[k])
wall = (time.perf_counter() - t) * 1e3 / 100
s = field.stats()
print(f"plain: wall {wall:.3f} ms per update; stats update_wall_ms {s['update_wall_ms']}; stages {s['times_ms']}")
print("captures", s["graph_captures"], "measured", s["measured_frames"], "moves", s["domain_moves"], "replans", s["replans"])
pr = cProfile.Profile()
pr.enable()
for k in range(130, 230):
    field.update(frames[k])
pr.disable()
out = io.StringIO()
st = pstats.Stats(pr, stream=out); st.sort_stats("tottime").print_stats(30)
st.sort_stats("cumulative").print_stats(45)
print(out.getvalue())
# a finer look: time each phase of update by hand
from badf.server.adf._inputs import as_vertices
t0 = time.perf_counter(); 
for k in range(100): as_vertices(frames[k], expected_count=len(v))
print(f"as_vertices {(time.perf_counter()-t0)*10:.4f} ms")
t0 = time.perf_counter()
for k in range(100): field._bounds(frames[k])
print(f"_bounds {(time.perf_counter()-t0)*10:.4f} ms")
host = field._staging
t0 = time.perf_counter()
for k in range(100): host.numpy()[:] = frames[k]
print(f"pinned write {(time.perf_counter()-t0)*10:.4f} ms")
