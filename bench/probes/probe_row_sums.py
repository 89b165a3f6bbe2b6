"""Probe: a mesh whose large triangles' shared rows pass int32 in all still gets every cell it crosses.

The surface-cell stage shares the rows of each triangle more than a few columns across among its threads,
through int32 running sums. Millions of such triangles at depth 10 would pass 2^31 rows; the rows shared
are capped for that. This builds N flat slivers (each about `resolution` rows long and a column wide) side
by side in one plane, so that N times the rows passes 2^31, and checks that the finest cells of points
sampled on the slivers are all in the octree.

    python bench/probes/probe_row_sums.py --device cuda:0 --slivers 2800000 --depth 10

It needs a GPU for the sizes that pass 2^31 (the CPU takes minutes); prints one line and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def slivers(count: int, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` slivers in the plane z = 0.5 along x, side by side in y over [0, 1], each 1/(4 resolution) wide."""
    y = (np.arange(count) + 0.5) / count
    width = 0.25 / resolution
    vertices = np.empty((count, 3, 3))
    vertices[:, 0] = np.stack([np.zeros(count), y, np.full(count, 0.5)], axis=1)
    vertices[:, 1] = np.stack([np.ones(count), y, np.full(count, 0.5)], axis=1)
    vertices[:, 2] = np.stack([np.ones(count), y + width, np.full(count, 0.5)], axis=1)
    # and a small triangle above them, so the domain's centre (a cell boundary) is off their plane
    vertices = np.concatenate([vertices.reshape(-1, 3), [[0, 0, 0.87], [0.01, 0, 0.87], [0, 0.01, 0.87]]])
    return vertices, np.arange(3 * count + 3, dtype=np.int32).reshape(-1, 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--slivers", type=int, default=2_800_000)
    parser.add_argument("--depth", type=int, default=10)
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    from badf.server.adf import DistanceField

    resolution = 1 << args.depth
    vertices, faces = slivers(args.slivers, resolution)
    start = time.perf_counter()
    field = DistanceField(vertices, faces, depth=args.depth, sign="none", halo=0, device=args.device)
    built_s = time.perf_counter() - start
    domain = field.info()["domain"]
    centre, side = np.asarray(domain["centre"]), float(domain["side"])
    levels, cells = field.octree_cells()
    finest = cells[levels == args.depth].astype(np.int64)
    keys = set((finest[:, 0] * resolution + finest[:, 1]) * resolution + finest[:, 2])

    # points on random slivers, away from their cells' faces so each lies in one cell only
    rng = np.random.default_rng(1)
    which = rng.integers(0, args.slivers, args.samples)
    a, b, c = (vertices[faces[which, k]] for k in range(3))
    r1, r2 = rng.random((2, args.samples, 1))
    flip = (r1 + r2) > 1
    r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
    points = a + r1 * (b - a) + r2 * (c - a)
    local = (points - (centre - side / 2)) / (side / resolution)
    clear = np.all(np.abs(local - np.round(local)) > 1e-3, axis=1)
    ijk = np.floor(local[clear]).astype(np.int64)
    sampled = (ijk[:, 0] * resolution + ijk[:, 1]) * resolution + ijk[:, 2]
    missed = int(sum(key not in keys for key in sampled.tolist()))

    rows_each = int(np.ceil(1.0 / (side / resolution)))
    result = {
        "device": args.device, "depth": args.depth, "slivers": args.slivers,
        "rows_per_sliver_about": rows_each, "rows_in_all_about": rows_each * args.slivers,
        "passes_int32": rows_each * args.slivers > 2**31 - 1,
        "surface_cells": int(field.stats()["counts"]["surface_cells"]), "sampled_cells": int(len(sampled)),
        "sampled_cells_missed": missed, "build_s": round(built_s, 2),
    }
    print(json.dumps(result))
    if args.out:
        with open(args.out, "w") as out:
            json.dump(result, out, indent=1)


if __name__ == "__main__":
    main()
