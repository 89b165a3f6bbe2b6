"""Probe, not part of the product: what the winding walks' budget (WINDING_BUDGET) does to a violent frame.

    python3 bench/probes/probe_winding_budget.py MESH.npz [MESH.npz ...] [--device cuda:0] [--depth 7]
        [--budgets 2048 1073741824] [--rounds 2] [--noise 0.2] [--out F.json]

For each mesh and budget (alternated over rounds, all in one process: the budget is a field of the BVH's view, so the
kernels are the same): an object at `depth` (rigid frames off) takes three calm frames, then one violent frame, every
vertex thrown up to `noise` of the box's extent and kept in the box (as `badf bench engine`'s violent row). The violent
frame's wall time, its walks cut, and against the first budget's field at that frame: how many corners changed side
and the largest difference in magnitude (the searches do not depend on the budget, so it should be 0).
"""

import argparse
import json
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 3)[0])
from badf.bench._common import deform, find_mesh, start_warp  # noqa: E402
from badf.server.adf import DistanceField, _bvh  # noqa: E402


def violent_frame(vertices: np.ndarray, noise: float) -> np.ndarray:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    throw = np.random.default_rng(0).uniform(-1.0, 1.0, size=vertices.shape) * noise * float(np.max(hi - lo))
    return np.clip(vertices + throw, lo, hi).astype(vertices.dtype)


def run_one(vertices, faces, *, depth: int, device: str, budget: int, noise: float) -> dict:
    _bvh.WINDING_BUDGET = budget  # read when the object's BVH is made
    field = DistanceField(vertices, faces, depth=depth, device=device, rigid="off")
    for k in range(1, 4):
        field.update(deform(vertices, 0.02 * k))
    wp.synchronize_device(device)
    start = time.perf_counter()
    field.update(violent_frame(vertices, noise))
    wp.synchronize_device(device)
    wall = time.perf_counter() - start
    stats = field.stats()
    _, values, _ = field.corner_samples()
    return {"budget": budget, "violent_wall_s": round(wall, 4), "winding_walks_cut": stats["winding_walks_cut"],
            "corners": stats["counts"]["unique_corners"], "values": values}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="+")
    parser.add_argument("--device", default=None)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--budgets", type=int, nargs="+", default=[2048, 2**30])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--noise", type=float, default=0.2)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    device = start_warp(args.device)
    report = {"device": wp.get_device(device).name, "depth": args.depth, "noise": args.noise, "rows": []}
    for mesh in args.meshes:
        data = np.load(find_mesh(mesh))
        vertices = data["vertices"][0] if data["vertices"].ndim == 3 else data["vertices"]
        vertices, faces = np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(data["faces"], np.int32)
        first = None
        for round_index in range(args.rounds):
            for budget in args.budgets:
                row = run_one(vertices, faces, depth=args.depth, device=device, budget=budget, noise=args.noise)
                values = row.pop("values")
                if first is None:
                    first = values
                row["sides_changed"] = int(np.sum((values < 0) != (first < 0)))
                row["largest_magnitude_difference"] = float(np.max(np.abs(np.abs(values) - np.abs(first))))
                row.update(mesh=mesh, faces=len(faces), round=round_index)
                report["rows"].append(row)
                print(json.dumps(row), flush=True)
    print(f"\n{report['device']}, depth {args.depth}, violent frame (noise {args.noise:g}):")
    print(f"{'mesh':>16} {'budget':>11} {'wall s':>8} {'walks cut':>10} {'corners':>9} {'sides changed':>14}")
    for r in report["rows"]:
        print(f"{r['mesh'][-16:]:>16} {r['budget']:>11} {r['violent_wall_s']:>8.3f} {r['winding_walks_cut']:>10} "
              f"{r['corners']:>9} {r['sides_changed']:>14}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
