"""Probe, not part of the product (python3 bench/probes/probe_register.py MESH.npz [device] [--repeat N]
[--profile]): a registration (the DistanceField constructor) by the wall clock, the median and least of N after one
that compiles the kernels; with --profile, where one constructor's host time goes (cProfile, by own time).
Whichever `badf` is on the path is timed, so two revisions alternate by PYTHONPATH (bench/interleave.py's package
roots)."""
import statistics
import sys

import numpy as np
import warp as wp

from badf.server.adf import DistanceField

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import constructor_profile, timed_constructions  # noqa: E402

args = [a for a in sys.argv[1:] if not a.startswith("--")]
repeat = int(sys.argv[sys.argv.index("--repeat") + 1]) if "--repeat" in sys.argv else 9
if str(repeat) in args:
    args.remove(str(repeat))
path, device = args[0], (args[1] if len(args) > 1 else "cuda:0")
mesh = np.load(path)
vertices = mesh["vertices"][0] if mesh["vertices"].ndim == 3 else mesh["vertices"]
vertices, faces = vertices.astype(np.float32), mesh["faces"].astype(np.int32)
wp.init()
DistanceField(vertices, faces, device=device)
walls, _ = timed_constructions(vertices, faces, device, repeat)
print(f"badf from {sys.modules['badf.server.adf'].__file__}")
print(f"{path} on {device}: constructor median {statistics.median(walls):.1f} ms, least {min(walls):.1f} "
      f"({repeat} runs: {', '.join(f'{w:.0f}' for w in walls)})", flush=True)
if "--profile" in sys.argv:
    text = constructor_profile(vertices, faces, device, own=15, cumulative=25)
    print("\n".join(line for line in text.splitlines() if line.strip())[:9000])
