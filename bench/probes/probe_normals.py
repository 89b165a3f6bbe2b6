"""Probe, not part of the product (python3 bench/probes/probe_normals.py OUT.json [device]; meshes from
$BADF_SHARED_DATA; results in docs/results/normals-*): what ADF normals near the surface cost and how many
point where the signed distance falls (a step along them goes deeper), on a smooth scan and on parts with
sharp edges; and what normals cost at points spread over the mesh's bounding box. Runs whichever badf is installed, so one file times the engine before and after a change."""
import json
import os
import sys
import time

import numpy as np
import warp as wp

from badf.server.adf import DistanceField

MESHES = (("stanford-bunny", 7), ("armadillo-86k", 7), ("fandisk", 6))
POINTS = 65536
REPEAT = 20


def near_surface(vertices, faces, count, spread, rng):
    """Uniform points on the surface, moved by a normal spread of `spread` on each axis, in random order."""
    tri = vertices[faces].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(faces), count, p=area / area.sum())
    r1, r2 = rng.random((2, count))
    flip = r1 + r2 > 1.0
    r1, r2 = np.where(flip, 1.0 - r1, r1), np.where(flip, 1.0 - r2, r2)
    t = tri[pick]
    points = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
    return (points + rng.normal(size=points.shape) * spread).astype(np.float32)


def median_ms(call, repeat=REPEAT):
    call()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def main() -> None:
    out, device = sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
    folder = os.environ.get("BADF_SHARED_DATA", "../shared/data")
    wp.init()
    rows = []
    for name, depth in MESHES:
        data = np.load(f"{folder}/{name}.npz")
        vertices, faces = data["vertices"].astype(np.float32), data["faces"].astype(np.int32)
        if vertices.ndim == 3:
            vertices = vertices[0]
        field = DistanceField(vertices, faces, depth=depth, device=device)
        cell = field.info()["domain"]["finest_cell"]
        points = near_surface(vertices, faces, POINTS, cell, np.random.default_rng(1))
        row = {"mesh": name, "depth": depth, "sign": field.info()["sign"], "points": POINTS}
        row["adf_distance_ms"] = median_ms(lambda: field.query(points, outputs=("distance",)))
        row["adf_normal_ms"] = median_ms(lambda: field.query(points, outputs=("distance", "normal")))
        row["exact_normal_ms"] = median_ms(lambda: field.query(points, mode="exact", outputs=("distance", "normal")))
        # the first query of a frame that asks for normals (it marks the leaves the medial surface crosses)
        first = []
        for _ in range(10):
            field.update(vertices)
            start = time.perf_counter()
            field.query(points, outputs=("distance", "normal"))
            first.append(time.perf_counter() - start)
        row["adf_normal_first_ms"] = 1e3 * float(np.median(first))
        got = field.query(points, outputs=("distance", "normal"))
        exact = field.query(points, mode="exact", outputs=("distance", "normal"))
        step = 0.05 * cell
        ahead = field.query(points + step * got.normal, mode="exact", outputs=("distance",))
        row["descents"] = int(np.count_nonzero(ahead.distance.astype(np.float64) - exact.distance < 0.0))
        row["against_exact"] = int(np.count_nonzero(np.einsum("ij,ij->i", got.normal, exact.normal) < 0.0))
        # points spread over the mesh's bounding box, most of them far from the surface
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        spread = (lo + (hi - lo) * np.random.default_rng(2).random((POINTS, 3))).astype(np.float32)
        row["box_distance_ms"] = median_ms(lambda: field.query(spread, outputs=("distance",)))
        row["box_normal_ms"] = median_ms(lambda: field.query(spread, outputs=("distance", "normal")))
        rows.append(row)
        print(json.dumps(row), flush=True)
    report = {"probe": "normals", "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "device": wp.get_device(device).name, "rows": rows}
    with open(out, "w") as f:
        json.dump(report, f, indent=1)
    print(f"{'mesh':>16} {'sign':>12} {'dist ms':>8} {'normal ms':>9} {'first ms':>8} {'exact ms':>8} "
          f"{'descents':>8} {'vs exact':>8} {'box dist':>8} {'box normal':>10}")
    for r in rows:
        print(f"{r['mesh']:>16} {r['sign']:>12} {r['adf_distance_ms']:8.3f} {r['adf_normal_ms']:9.3f} "
              f"{r['adf_normal_first_ms']:8.3f} {r['exact_normal_ms']:8.3f} {r['descents']:8d} {r['against_exact']:8d} "
              f"{r['box_distance_ms']:8.3f} {r['box_normal_ms']:10.3f}")


if __name__ == "__main__":
    main()
