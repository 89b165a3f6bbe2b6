"""Probe, not part of the product: what each of the BVH's shapes costs and buys on one device, alternated round by
round in one process, so that both meet the same machine.

    python bench/probes/probe_bvh_shapes.py MESH.npz [MESH.npz ...] [--device cpu] [--depths 5 7] [--rounds 3]
        [--frames 5] [--points 20000] [--out F.json]

Per round and shape (morton, sah): a registration (the constructor, by the wall clock, the SAH shape's host time
within it), three warm-up updates of the bench's wobble, `--frames` timed updates, and an exact query of `--points`
points spread over the mesh's box; the medians over rounds, and whether both shapes gave the same exact distances."""

import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

from badf.bench._common import deform
from badf.server.adf import DistanceField

SHAPES = ("morton", "sah")


def _wall(fn, device):
    wp.synchronize_device(device)
    started = time.perf_counter()
    out = fn()
    wp.synchronize_device(device)
    return (time.perf_counter() - started) * 1e3, out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("meshes", nargs="+")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--depths", type=int, nargs="+", default=[5, 7])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--points", type=int, default=20000)
    parser.add_argument("--out")
    args = parser.parse_args()
    wp.init()
    results = []
    for path in args.meshes:
        mesh = np.load(path)
        vertices = (mesh["vertices"][0] if mesh["vertices"].ndim == 3 else mesh["vertices"]).astype(np.float32)
        faces = mesh["faces"].astype(np.int32)
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        points = np.random.default_rng(1).uniform(lo, hi, (args.points, 3)).astype(np.float32)
        for depth in args.depths:
            DistanceField(vertices, faces, depth=depth, bvh="sah", device=args.device)  # compiles every kernel
            times = {shape: {"register": [], "shape": [], "update": [], "exact": []} for shape in SHAPES}
            answers = {}
            for _ in range(args.rounds):
                for shape in SHAPES:
                    t = times[shape]
                    ms, field = _wall(lambda: DistanceField(vertices, faces, depth=depth, bvh=shape,  # noqa: B023
                                                            device=args.device), args.device)
                    t["register"].append(ms)
                    t["shape"].append(field.stats()["bvh_shape_ms"] or 0.0)
                    for k in range(3 + args.frames):
                        ms, _ = _wall(lambda: field.update(deform(vertices, 0.05 * (k + 1))), args.device)  # noqa: B023
                        if k >= 3:
                            t["update"].append(ms)
                    ms, result = _wall(lambda: field.query(points, mode="exact"), args.device)  # noqa: B023
                    t["exact"].append(ms)
                    answers[shape] = np.abs(result.distance)
            row = {"mesh": path, "faces": len(faces), "depth": depth, "device": args.device,
                   "same_exact_distances": bool(np.array_equal(answers["morton"], answers["sah"]))}
            for shape in SHAPES:
                row[shape] = {key: round(statistics.median(values), 2) for key, values in times[shape].items()}
            results.append(row)
            m, s = row["morton"], row["sah"]
            print(f"{path} ({len(faces)} faces) depth {depth} on {args.device}: register {m['register']} / "
                  f"{s['register']} ms (shape {s['shape']}), update {m['update']} / {s['update']}, exact "
                  f"{args.points} points {m['exact']} / {s['exact']} (morton / sah, medians); same exact "
                  f"distances: {row['same_exact_distances']}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
