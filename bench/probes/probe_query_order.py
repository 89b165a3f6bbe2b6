"""Probe, not part of the product: batch queries walked in their points' Morton order against the caller's order.

    python3 bench/probes/probe_query_order.py MESH.npz [MESH.npz ...] [--device cuda:0] [--repeat K] [--out F.json]

A query kernel gives each thread one point; a warp of 32 points in the caller's order (uniform samples, the
vertices of another mesh) walks 32 unrelated paths of the BVH or the octree and lasts as long as the longest.
`PointQuery` sorts a batch of at least `ordered_from` points by Morton key on the device and walks it in that order
(`ordered_modes`). This times both, alternating query by query on one object, for three kinds of point set:
`uniform` in the mesh's bounding box, `near` (surface samples moved by 1% of the diagonal, shuffled) and `coherent`
(the same, in the mesh's face order: neighbouring rows are neighbouring points, as a cloth's vertices are), at
several batch sizes, ADF and exact, distance alone and all four outputs. Each row is the median wall time of K
queries of each, which includes the sort; every pair's answers are compared bit for bit.
"""

import argparse
import json
import pathlib
import statistics
import time

import numpy as np
import warp as wp

from badf.server.adf import DistanceField
from badf.server.adf import _distance

parser = argparse.ArgumentParser()
parser.add_argument("meshes", nargs="+")
parser.add_argument("--device", default="cuda:0")
parser.add_argument("--repeat", type=int, default=15)
parser.add_argument("--depth", type=int, default=7)
parser.add_argument("--sizes", type=int, nargs="*", default=[1_024, 4_096, 16_384, 65_536, 1_048_576])
parser.add_argument("--registers", type=int, nargs="*", default=[],
                    help="also time the query kernel capped at these register counts (0: uncapped), Morton order")
parser.add_argument("--out")
args = parser.parse_args()

wp.init()
OUTPUTS = {"distance": ("distance",), "all": ("distance", "closest_point", "normal", "face")}


def point_sets(vertices, faces, count, rng):
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    tri = vertices[faces].astype(np.float64)
    chosen = np.sort(rng.integers(0, len(faces), count))  # face order: neighbouring rows, neighbouring points
    u, v = rng.random((2, count))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    on = tri[chosen, 0] + u[:, None] * (tri[chosen, 1] - tri[chosen, 0]) + v[:, None] * (tri[chosen, 2] - tri[chosen, 0])
    coherent = on + rng.normal(scale=0.01 * diagonal, size=on.shape)
    return {
        "uniform": rng.uniform(lo, hi, (count, 3)).astype(np.float32),
        "near": coherent[rng.permutation(count)].astype(np.float32),
        "coherent": coherent.astype(np.float32),
    }


def timed(field, points, mode, outputs, ordered):
    field._points.ordered_from = 1  # the probe picks per query; the engine's own thresholds are what it measures
    field._points.ordered_modes = {mode} if ordered else set()
    start = time.perf_counter()
    result = field.query(points, mode=mode, outputs=outputs)
    return (time.perf_counter() - start) * 1e3, result


rows = []
mismatches = 0
for path in args.meshes:
    mesh = np.load(path)
    vertices, faces = mesh["vertices"].astype(np.float32), mesh["faces"].astype(np.int32)
    field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
    name = pathlib.Path(path).stem
    sets = point_sets(vertices, faces, max(args.sizes, default=1), np.random.default_rng(0))
    for size in args.sizes:
        for kind, points in sets.items():
            if size > 65_536 and kind == "near":
                continue
            batch = np.ascontiguousarray(points[:size]) if kind != "uniform" or size == len(points) else points[:size]
            for mode in ("adf", "exact"):
                for label, outputs in OUTPUTS.items():
                    if label == "all" and size != 65_536:
                        continue
                    for ordered in (False, True):  # warm-up: kernels, buffers
                        timed(field, batch, mode, outputs, ordered)
                    times = {False: [], True: []}
                    for k in range(args.repeat):
                        for ordered in ((False, True) if k % 2 == 0 else (True, False)):
                            ms, result = timed(field, batch, mode, outputs, ordered)
                            times[ordered].append(ms)
                            if k == 0:
                                if ordered:
                                    got = result
                                else:
                                    want = result
                    same = all(np.array_equal(getattr(got, o), getattr(want, o)) for o in outputs)
                    mismatches += not same
                    row = {"mesh": name, "points": kind, "size": size, "mode": mode, "outputs": label,
                           "caller_ms": statistics.median(times[False]), "morton_ms": statistics.median(times[True]),
                           "identical": same}
                    rows.append(row)
                    print(f"{name:16s} {kind:9s} {size:>9,d} {mode:5s} {label:8s} caller {row['caller_ms']:8.3f} ms"
                          f"  morton {row['morton_ms']:8.3f} ms  x{row['caller_ms'] / row['morton_ms']:5.2f}"
                          f"  {'same' if same else 'DIFFERENT'}", flush=True)


def capped(registers):
    """The query kernels compiled again under a register cap (0: the compiler's choice)."""
    _distance.QUERY_MAX_REGISTERS = registers or None
    for key in [key for key in _distance._KERNELS if key[0] == "query"]:
        del _distance._KERNELS[key]


caps = []
if args.registers:  # the first mesh's uniform 65,536 points, each cap in turn for several rounds, in both orders
    mesh = np.load(args.meshes[0])
    vertices, faces = mesh["vertices"].astype(np.float32), mesh["faces"].astype(np.int32)
    field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
    batch = point_sets(vertices, faces, 65_536, np.random.default_rng(1))["uniform"]
    times = {(r, mode, ordered): [] for r in args.registers for mode in ("adf", "exact") for ordered in (True, False)}
    for round_ in range(4):
        for registers in args.registers:
            capped(registers)
            for mode, ordered in [(mode, ordered) for mode in ("adf", "exact") for ordered in (True, False)]:
                timed(field, batch, mode, OUTPUTS["all"], ordered)
                times[registers, mode, ordered] += [timed(field, batch, mode, OUTPUTS["all"], ordered)[0]
                                                    for _ in range(args.repeat)]
    capped(0)
    for (registers, mode, ordered), values in times.items():
        caps.append({"registers": registers, "mode": mode, "order": "morton" if ordered else "caller",
                     "ms": statistics.median(values)})
        print(f"registers {registers or 'uncapped':>8} {mode:5s} {'morton' if ordered else 'caller'} order,"
              " all outputs 65,536 uniform: "
              f"{statistics.median(values):8.3f} ms", flush=True)

device = wp.get_device(args.device)
print(f"{device.name} {time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime())} UTC; mismatching pairs: {mismatches}")
if args.out:
    pathlib.Path(args.out).write_text(json.dumps({"device": device.name, "rows": rows, "mismatches": mismatches,
                                                  "repeat": args.repeat, "depth": args.depth,
                                                  "caps": caps}, indent=1))
