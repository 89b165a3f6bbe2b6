"""Probe, not part of the product (python3 bench/probes/probe_far_pull.py MESH.npz [device]): exact queries of
points far from a mesh, with far points moved in from 2^40, 2^20 or 2^16 domain sides (`FAR_POINT`), in one
process: the time per batch and the error against the float64 oracle, in float32 spacings of the true distance.

Beyond about 1e6 sides float32 rounds the distances to a mesh's faces alike to an ulp or two. The searches then
cannot prune, and exact queries 5e8 sides from the bunny took 100 times as long as near it (CPU, 2026-12-02). A
point moved in to FAR_POINT sides is searched where its faces still differ, and the move changes its distance by
at most r^2 / (2 FAR_POINT) for a mesh within r of the centre.
"""
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 3)[0] + "/tests")
import oracle  # noqa: E402

import badf.server.adf._field as field_module  # noqa: E402
from badf.server.adf import DistanceField  # noqa: E402

LIMITS = (2.0**40, 2.0**20, 2.0**16)


def main() -> None:
    path = sys.argv[1]
    device = sys.argv[2] if len(sys.argv) > 2 else "cpu"
    wp.config.quiet = True
    data = np.load(path)
    vertices = np.asarray(data["vertices"], np.float64)
    if vertices.ndim == 3:
        vertices = vertices[0]
    faces = data["faces"]
    field = DistanceField(vertices, faces, depth=6, device=device)
    side = field.info()["domain"]["side"]
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(5000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    centre = np.asarray(field.info()["domain"]["centre"])
    kept = field_module.FAR_POINT
    print(f"{path}: {len(faces)} faces, domain side {side:.4g}, 5,000 points a batch ({device}); "
          "ms for the batch, then the largest error in float32 spacings of the true distance (400 points)")
    print(f"{'sides away':>12}" + "".join(f"{'2^' + str(int(np.log2(limit))) + ' ms':>12}{'spacings':>10}"
                                          for limit in LIMITS))
    try:
        for sides in (1.0, 1e4, 1e6, 1e7, 1e8, 1e10, 1e13):
            points = centre + directions * sides * side
            truth = oracle.nearest(points[:400], vertices, faces).distance
            spacing = np.spacing(truth.astype(np.float32)).astype(np.float64)
            row = f"{sides:>12.0e}"
            for limit in LIMITS:
                field_module.FAR_POINT = limit
                field.query(points[:100], mode="exact")
                started = time.perf_counter()
                result = field.query(points, mode="exact", outputs=("distance", "face"))
                ms = (time.perf_counter() - started) * 1e3
                error = np.abs(result.distance[:400].astype(np.float64) - truth) / spacing
                row += f"{ms:>12.0f}{error.max():>10.2f}"
            print(row, flush=True)
    finally:
        field_module.FAR_POINT = kept


if __name__ == "__main__":
    main()
