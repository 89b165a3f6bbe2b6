"""Probe: whether the queries' search names the least face from any start, far off flat-faced meshes.

Off a box meshed in axis-aligned squares many faces lie within an ulp or two of each other when seen from
30 to 3,000 sizes away. For boxes meshed three ways and points in three families of directions, this
starts the queries' search from four seeds per point (leaf 0, the last leaf, two at random) and counts the
searches that name another leaf than the least over all leaves, valued as the search values them. Before
2026-11-23 (the search valued a leaf by its triangle's distance alone) 403 of 4,000 differed on the H100
for the first box's near-axis points (with this kernel compiled with fused multiply-adds; 332 on the
CPU); the engine's test of this is
`test_a_query_far_off_a_flat_faced_mesh_names_the_least_face_from_any_start`.

    python bench/probes/probe_tied_faces.py --device cuda:0
"""

import argparse

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--points", type=int, default=1000)
    args = parser.parse_args()

    import trimesh
    import warp as wp

    wp.config.quiet = True
    from badf.server.adf import DistanceField
    from badf.server.adf._bvh import BvhView, leaf_distance_held_to_box_sq, nearest_leaf_past_ties
    from badf.server.adf._distance import EXACT_ROUNDING

    @wp.kernel(module="unique", module_options=EXACT_ROUNDING)
    def searches(bvh: BvhView, points: wp.array(dtype=wp.vec3), seeds: wp.array2d(dtype=wp.int32),
                 found: wp.array2d(dtype=wp.int32), least: wp.array(dtype=wp.int32)):
        i = wp.tid()
        p = points[i]
        for k in range(seeds.shape[1]):
            seed = seeds[i, k]
            leaf, _d_sq, _done = nearest_leaf_past_ties(bvh, p, seed, leaf_distance_held_to_box_sq(bvh, seed, p),
                                                        2147483647)
            found[i, k] = leaf
        best = int(0)
        best_sq = leaf_distance_held_to_box_sq(bvh, 0, p)
        for leaf in range(1, bvh.internal_count + 1):
            d_sq = leaf_distance_held_to_box_sq(bvh, leaf, p)
            if d_sq < best_sq:
                best = leaf
                best_sq = d_sq
        least[i] = best

    n = args.points
    print(f"{'subdivisions':>12} {'extents':>16} {'directions':>10} {'faces':>6} {'differ':>7} of {4 * n}")
    for subdivisions, extents in ((3, (1.0, 0.7, 0.4)), (4, (1.0, 1.0, 1.0)), (2, (2.0, 1.0, 1.0))):
        box = trimesh.creation.box(extents=extents)
        for _ in range(subdivisions):
            box = box.subdivide()
        vertices, faces = np.asarray(box.vertices), np.asarray(box.faces)
        field = DistanceField(vertices, faces, depth=2, sign="none", device=args.device)
        rng = np.random.default_rng(5)
        for family in ("rounded", "any", "near axes"):
            directions = rng.normal(size=(n, 3))
            if family == "rounded":
                directions = np.round(directions)
            if family == "near axes":
                directions = (np.eye(3)[rng.integers(0, 3, n)] * rng.choice([-1, 1], (n, 1))
                              + rng.normal(0, 1e-3, (n, 3)))
            directions[np.all(directions == 0, axis=1)] = (1.0, 0.0, 0.0)
            points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * np.geomspace(30, 3e3, n)[:, None]
            leaves = len(faces)
            seeds = np.stack([np.zeros(n), np.full(n, leaves - 1), rng.integers(0, leaves, n),
                              rng.integers(0, leaves, n)], axis=1).astype(np.int32)
            found = wp.zeros(seeds.shape, dtype=wp.int32, device=args.device)
            least = wp.zeros(n, dtype=wp.int32, device=args.device)
            wp.launch(searches, dim=n, inputs=[field._bvh.view(),
                                                wp.array(field._domain.to_local(points), dtype=wp.vec3,
                                                         device=args.device),
                                                wp.array(seeds, dtype=wp.int32, device=args.device)],
                      outputs=[found, least], device=args.device)
            differ = np.count_nonzero(found.numpy() != least.numpy()[:, None])
            print(f"{subdivisions:>12} {str(extents):>16} {family:>10} {leaves:>6} {differ:>7}")


if __name__ == "__main__":
    main()
