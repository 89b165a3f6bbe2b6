"""Probe: ADF error beside an open mesh's opening, and what answering jump leaves exactly buys and costs.

An open mesh's winding-number sign jumps off the surface across each opening, and beside the rim the jump runs
through finest leaves the surface also crosses. A signed distance changes no faster than its argument wherever its
sign does not jump, so two corners of a leaf with opposite signs whose distances add up to more than the corners
are apart straddle a jump. Two rules find such leaves:
- "diagonal": the deepest corner inside and the farthest outside add up to more than the leaf's diagonal (no two
  corners are farther apart). The query kernel answers points in such leaves exactly since 2026-12-07.
- "pairs": any two corners of opposite signs add up to more than they are apart (finds more; tried on the CPU,
  docs/results/rim-jumps-cpu-2215, not kept).
- "rim": the leaf is a finest cell the rim passes through (`bench._cases.rim_cells`), where the winding number
  takes every value from 0 to 1 whatever the corners read. The query kernel answers points in leaves the rim
  crosses exactly since 2026-12-08 (`mark_rim_leaves`, which marks a few cells beside the rim too).
This finds the leaves of each rule on the host, from the field's own corner values (`corner_samples`,
`octree_cells`), for points within a finest cell of the surface (of a bowl's rim, and of the whole bunny), and
prints against the float64 oracle, in finest cells: the ADF's error as served, and as it would be with the points
of each rule's leaves answered exactly (exact mode's answers put in their place); how many points each rule
takes; and the time of an ADF and an exact query of all the points (a rule's price is its share of points times
the exact query's price per point).

    python bench/probes/probe_rim_jumps.py --device cpu
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from badf.bench import _oracle as oracle
from badf.bench._cases import CORNER_OFFSETS, domain_of, finest_leaf_corners, rim_cells

_APART = np.sqrt(np.abs(CORNER_OFFSETS[:, None, :] - CORNER_OFFSETS[None, :, :]).sum(axis=2))  # in cells


def straddling(field, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> dict[str, np.ndarray]:
    """Whether each point lies in a finest leaf where the sign may jump, by each rule (the docstring)."""
    centre, side, cell = domain_of(field)
    v = finest_leaf_corners(field, points)  # NaN rows outside finest leaves: neither side, so no rule holds
    inside, outside = v < 0, v >= 0
    both = inside.any(axis=1) & outside.any(axis=1)
    deepest = np.where(inside, -v, 0.0).max(axis=1)
    farthest_out = np.where(outside, v, 0.0).max(axis=1)
    opposite = (inside[:, :, None] & outside[:, None, :]) | (outside[:, :, None] & inside[:, None, :])
    far = np.abs(v)[:, :, None] + np.abs(v)[:, None, :] > _APART * cell * 1.0001
    crossed = rim_cells(field, vertices, faces)
    at = np.floor((np.asarray(points, np.float64) - (centre - side / 2.0)) / cell).astype(np.int64)
    return {"diagonal": both & (deepest + farthest_out > np.sqrt(3.0) * cell * 1.0001),
            "pairs": np.any(opposite & far, axis=(1, 2)),
            "rim": np.fromiter(map(crossed.__contains__, map(tuple, at)), bool, len(at))}


def within_a_cell(anchors: np.ndarray, cell: float, rng: np.random.Generator) -> np.ndarray:
    direction = rng.normal(size=anchors.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return anchors + direction * rng.random((len(anchors), 1)) * cell


def median_ms(run, repeats: int = 5) -> float:
    run()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--bunny", default="../shared/data/stanford-bunny.npz")
    parser.add_argument("--points", type=int, default=3000)
    args = parser.parse_args()

    import trimesh
    import warp as wp

    wp.config.quiet = True
    from badf.server.adf import DistanceField

    sphere = trimesh.creation.icosphere(4)
    bowl = np.asarray(sphere.vertices), np.asarray(sphere.faces)[sphere.triangles_center[:, 2] < 0.0]
    data = np.load(args.bunny)
    bunny = data["vertices"].astype(np.float64), data["faces"]
    cases = [("bowl rim", *bowl, depth) for depth in (4, 5, 6)] + [("bunny surface", *bunny, depth) for depth in (6, 7)]
    for label, vertices, faces, depth in cases:
        field = DistanceField(vertices, faces, depth=depth, sign="winding", device=args.device)
        cell = field.info()["domain"]["finest_cell"]
        rng = np.random.default_rng(5)
        if label == "bowl rim":
            angle = rng.uniform(0.0, 2.0 * np.pi, args.points)
            anchors = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
        else:
            tri = vertices[faces[rng.integers(0, len(faces), args.points)]]
            weights = rng.dirichlet([1.0, 1.0, 1.0], size=args.points)
            anchors = np.einsum("pk,pkd->pd", weights, tri)
        points = within_a_cell(anchors, cell, rng)
        truth = oracle.signed_distance(points, vertices, faces)
        adf = field.query(points, mode="adf").distance
        exact = field.query(points, mode="exact").distance
        error = np.abs(adf - truth) / cell
        row = {"case": label, "depth": depth, "points": len(points),
               "adf_max_error_cells": round(float(error.max()), 3), "adf_over_one_cell": int((error >= 1.0).sum()),
               "adf_answered_exactly": int((adf == exact).sum())}
        rules = straddling(field, points, vertices, faces)
        rules["diagonal+rim"] = rules["diagonal"] | rules["rim"]
        for rule, jump in rules.items():
            fixed = np.abs(np.where(jump, exact, adf) - truth) / cell
            row[rule] = {"points": int(jump.sum()), "max_error_cells": round(float(fixed.max()), 3),
                         "over_one_cell": int((fixed >= 1.0).sum())}
        batch = points.astype(np.float32)
        row.update({
            "adf_query_ms": round(median_ms(lambda: field.query(batch, mode="adf")), 3),
            "exact_query_ms": round(median_ms(lambda: field.query(batch, mode="exact")), 3),
        })
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
