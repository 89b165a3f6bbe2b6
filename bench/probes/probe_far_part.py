"""Probe: exact queries near a mesh, with and without one small triangle far from it.

The BVH orders triangles by the Morton code of their centroids in the domain, which a far part stretches: with
too few code bits the near part shares a few cells, its triangles are ordered by index, and searches near it
barely prune. This times exact queries at points near the mesh and a coherent update, for the mesh alone and
with a triangle `--ratio` mesh sizes away, and prints the sum of the distances (the same with and without the
far part, up to the far part's effect on float32 rounding).

    python bench/probes/probe_far_part.py --mesh stanford-bunny.npz --device cuda:0
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", required=True, help=".npz with vertices (N, 3) and faces (M, 3)")
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--ratio", type=float, default=1000.0, help="the far triangle's distance in mesh sizes")
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    from badf.server.adf import DistanceField

    data = np.load(args.mesh)
    mesh_vertices, mesh_faces = data["vertices"].astype(np.float64), data["faces"]
    size = float(np.ptp(mesh_vertices, axis=0).max())
    centre = mesh_vertices.mean(axis=0)
    rng = np.random.default_rng(0)
    points = mesh_vertices[rng.integers(0, len(mesh_vertices), args.points)]
    points = (points + rng.normal(size=points.shape) * 0.01 * size).astype(np.float32)
    for ratio in (None, args.ratio):
        vertices, faces = mesh_vertices, mesh_faces
        if ratio is not None:
            far = centre + np.array([ratio * size, 0.0, 0.0])
            vertices = np.vstack([mesh_vertices, far, far + [0.01 * size, 0, 0], far + [0, 0.01 * size, 0]])
            faces = np.vstack([mesh_faces, [[len(mesh_vertices), len(mesh_vertices) + 1, len(mesh_vertices) + 2]]])
        field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
        field.query(points[:1000], mode="exact")
        wp.synchronize()
        times = []
        for _ in range(3):
            start = time.perf_counter()
            result = field.query(points, mode="exact")
            times.append(time.perf_counter() - start)
        updates = []
        for k in range(5):
            start = time.perf_counter()
            field.update(vertices * (1.0 + 1e-4 * (k + 1)))
            updates.append(time.perf_counter() - start)
        total = float(np.sum(np.abs(result.distance.astype(np.float64))))
        print(f"far part {ratio}: exact {len(points)} near points {1e3 * np.median(times):.2f} ms, "
              f"update wall {1e3 * np.median(updates):.2f} ms, sum of |distances| {total:.6e}", flush=True)


if __name__ == "__main__":
    main()
