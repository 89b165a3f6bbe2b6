"""Probe, not part of the product (python3 bench/probes/probe_build.py MESH.npz [device] [--out FILE]): where a
build's device time goes. `badf bench engine` times a build's first frame by events (6 to 7 ms for the bunny on an
H200) against 2.1 ms for an update replayed from a graph; engine.md guesses the difference is the host's rate of
launches. This probe measures it instead, on CUDA:
- each activity (kernel, copy, fill) of a build, by Warp's CUDA activity timing: how many, how long on the device;
  the same for an eager update (kernels one by one, no graph) and the summed busy time against each one's span;
- the build's host work under cProfile: where the constructor's wall time goes, and how many launches it makes.
Nothing here is asserted: it prints tables and, with --out, writes them as JSON."""
import json
import sys
import time

import numpy as np
import warp as wp

wp.config.quiet = True
from badf.bench._common import deform  # noqa: E402
from badf.server.adf import DistanceField  # noqa: E402

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import constructor_profile, mesh_device_out  # noqa: E402

path, device, out = mesh_device_out()
REPEAT = 6
mesh = np.load(path)
vertices, faces = mesh["vertices"].astype(np.float32), mesh["faces"]


def timed(step):
    """(wall ms, activities) of one step, its CUDA activity recorded."""
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    start = time.perf_counter()
    result = step()
    wp.synchronize_device(device)
    wall = (time.perf_counter() - start) * 1e3
    return wall, wp.timing_end(), result


def summary(runs):
    """Per activity name: launches and device ms per run, with each run's busy sum and span."""
    per_name = {}
    for _, activities, _ in runs:
        for a in activities:
            per_name.setdefault(a.name, []).append(a.elapsed)
    rows = sorted(((n, len(t) / len(runs), sum(t) / len(runs)) for n, t in per_name.items()), key=lambda r: -r[2])
    return {
        "wall_ms": float(np.median([w for w, _, _ in runs])),
        "busy_ms": float(np.median([sum(a.elapsed for a in acts) for _, acts, _ in runs])),
        "activities_per_run": round(sum(r[1] for r in rows), 1),
        "activities": [{"name": n, "per_run": round(c, 2), "ms": round(t, 4)} for n, c, t in rows],
    }


def show(title, s, top=30):
    print(f"\n{title}: wall {s['wall_ms']:.3f} ms, device busy {s['busy_ms']:.3f} ms, "
          f"{s['activities_per_run']} activities a run")
    for a in s["activities"][:top]:
        print(f"  {a['ms']:8.4f} ms  {a['per_run']:6.1f}x  {a['name'][:90]}")


field = DistanceField(vertices, faces, device=device)  # compiles the kernels
field.update(deform(vertices, 0.5))
builds = [timed(lambda: DistanceField(vertices, faces, device=device)) for _ in range(REPEAT)]
spans = [b[2].stats()["times_ms"] for b in builds]
build = summary(builds)
build["first_frame_span_ms"] = float(np.median([s["total"] for s in spans]))
build["stages_ms"] = {k: float(np.median([s[k] for s in spans])) for k in spans[0]}
show("build (constructor)", build)
print("  first frame's span by events:", round(build["first_frame_span_ms"], 3), "ms; stages", build["stages_ms"])

eager = builds[-1][2]
eager.use_graphs = False
eager.update(deform(vertices, 0.51))
updates = [timed(lambda k=k: eager.update(deform(vertices, 0.52 + 0.01 * k))) for k in range(REPEAT)]
update = summary(updates)
show("eager update (kernels one by one)", update, top=12)

host_profile = constructor_profile(vertices, faces, device, own=30, cumulative=40)
print(host_profile)

if out:
    with open(out, "w") as f:
        json.dump({"probe": "build", "device": wp.get_device(device).name, "mesh": path,
                   "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                   "build": build, "eager_update": update, "host_profile": host_profile}, f, indent=1)
