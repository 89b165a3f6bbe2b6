"""Probe, not part of the product: calm frames after a violent frame that moves the domain, with the tree linked again
once it misfits (the engine) and without (the host never acting on the device's verdict, `tree_fit`: the walks on the
misfit tree are still bound there, as in the engine).

    python3 bench/probes/probe_relink.py MESH.npz [MESH.npz ...] [--device cuda:0] [--depth 7] [--frames 10]
        [--out F.json]

A violent frame that moves the domain links the Morton tree on its soup of triangles. For each mesh and setting, in
one process: `frames` calm frames (`deform`), the violent frame (every vertex thrown up to 0.2 of the box's extent,
not kept in the box), then `frames` calm frames again; each frame's wall time, an exact query of 65,536 points
before and after, the relinks, the leaf spread and the winding walks cut, and how the last frame's exact answers
differ from a fresh object's.
"""

import argparse
import json
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 3)[0])
from badf.bench._common import deform, find_mesh, start_warp  # noqa: E402
from badf.server.adf import DistanceField  # noqa: E402
from badf.server.adf import _bvh, _field  # noqa: E402


def timed(device, call):
    wp.synchronize_device(device)
    start = time.perf_counter()
    result = call()
    wp.synchronize_device(device)
    return result, round((time.perf_counter() - start) * 1e3, 3)


def run(vertices, faces, *, depth, device, frames, relink):
    # the levels of the report's verdict the host links at (TREE_DUE) and runs a frame again at (TREE_MISFITS); a
    # level above every verdict turns both off
    never = int(_bvh.TREE_MISFITS) + 1
    _field.TREE_DUE, _field.TREE_MISFITS = (_bvh.TREE_DUE, _bvh.TREE_MISFITS) if relink else (never, never)
    field = DistanceField(vertices, faces, depth=depth, device=device, bvh="morton", rigid="off")
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    points = np.random.default_rng(3).uniform(vertices.min(axis=0), vertices.max(axis=0), (65536, 3)).astype(np.float32)
    calm = [deform(vertices, 0.02 * k) for k in range(2 * frames + 3)]
    for frame in calm[:3]:
        field.update(frame)
    before = [timed(device, lambda f=f: field.update(f))[1] for f in calm[3:3 + frames]]
    _, query_before = timed(device, lambda: field.query(points, mode="exact"))
    thrown = (vertices + np.random.default_rng(0).uniform(-0.2, 0.2, vertices.shape) * extent).astype(np.float32)
    _, violent = timed(device, lambda: field.update(thrown))
    after, spread, cut = [], [], []
    for frame in calm[3 + frames:]:
        after.append(timed(device, lambda f=frame: field.update(f))[1])
        stats = field.stats()
        spread.append(stats["bvh_leaf_spread"])
        cut.append(stats["winding_walks_cut"])
    _, query_after = timed(device, lambda: field.query(points, mode="exact"))
    fresh = DistanceField(calm[-1], faces, depth=depth, device=device, bvh="morton", rigid="off")
    # the domain moved, so the corners are not a fresh object's: compare exact answers at the points
    ours = field.query(points, mode="exact").distance
    theirs = fresh.query(points, mode="exact").distance
    return {"relink": relink, "calm_before_ms": before, "violent_ms": violent, "calm_after_ms": after,
            "spread_after": spread, "walks_cut_after": cut, "exact_query_before_ms": query_before,
            "exact_query_after_ms": query_after, "relinks": field.stats()["bvh_relinks"],
            "domain_moves": field.stats()["domain_moves"],
            "exact_largest_difference_from_fresh": float(np.max(np.abs(ours - theirs))),
            "sides_differing_from_fresh": int(np.sum((ours < 0) != (theirs < 0)))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="+")
    parser.add_argument("--device", default=None)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    device = start_warp(args.device)
    report = {"device": wp.get_device(device).name, "depth": args.depth, "rows": []}
    for mesh in args.meshes:
        data = np.load(find_mesh(mesh))
        vertices = np.ascontiguousarray(data["vertices"], np.float32)
        faces = np.ascontiguousarray(data["faces"], np.int32)
        for relink in (True, False):
            row = run(vertices, faces, depth=args.depth, device=device, frames=args.frames, relink=relink)
            row["mesh"] = mesh
            report["rows"].append(row)
            print(json.dumps(row), flush=True)
    print(f"\n{report['device']}, depth {args.depth}: calm frames before and after a violent frame that moves the domain")
    print(f"{'mesh':>16} {'relink':>6} {'before ms':>9} {'violent ms':>10} {'first after':>11} {'rest after':>10} "
          f"{'query ms before/after':>22} {'relinks':>7} {'sides off fresh':>15}")
    for r in report["rows"]:
        print(f"{r['mesh'][-16:]:>16} {str(r['relink']):>6} {np.median(r['calm_before_ms']):>9.2f} "
              f"{r['violent_ms']:>10.1f} {r['calm_after_ms'][0]:>11.2f} {np.median(r['calm_after_ms'][1:]):>10.2f} "
              f"{r['exact_query_before_ms']:>10.2f} / {r['exact_query_after_ms']:<9.2f} {r['relinks']:>7} "
              f"{r['sides_differing_from_fresh']:>15}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
