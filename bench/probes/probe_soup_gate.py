"""Probe, not part of the product: what binding the winding walks' budget only to soups (SOUP_AREA) costs and buys.

    python3 bench/probes/probe_soup_gate.py [MESH.npz ...] [--device cuda:0] [--depth 7] [--sections 2000]
        [--noise 0.02 0.05 0.2] [--fractions 1.0] [--fat-areas 0.05 0.2] [--rounds 2] [--out F.json]

Cases: a closed cylinder of `--sections` sections (long thin triangles, a sound surface whose walks open more nodes
than the budget) and an open sheet of strips folded into `--layers` layers (sound, but a soup by its area), both signed
by winding numbers, and each mesh's frame with every vertex thrown up to each `--noise` of
the box's extent, kept in the box, after three calm frames (sign "auto"); with `--fractions` below 1, only that share
of the vertices (picked at random) is thrown: a frame only part of which is violent. Each case runs under four or five settings,
alternated over rounds in one process (the settings are fields of the BVH's view, read when an object is made):

    gated   the engine's: the budget binds where the frame's area passes SOUP_AREA sphere areas, and counts only the
            nodes of more than FAT_AREA times their disc's area
    every   the budget binds there, and every node counts (the engine before FAT_AREA)
    always  the budget binds every walk, and every node counts (the engine before SOUP_AREA)
    fat-always  the budget binds every walk, and counts only FAT_AREA's fat nodes (no soup gate; with --fat-always)
    never   no budget (the reference for the sides)
    fat=X   as gated, with FAT_AREA = X (one such setting for each of `--fat-areas`)

For each: the frame's wall time (synchronised), its walks cut, the frame's area in sphere areas (at the BVH's root),
and the corners whose side differs from "never"'s; for the cylinder also the corners off the surface whose side
differs from the solid's (inside: radius < 0.5 and |z| < 1).
"""

import argparse
import json
import sys
import time

import numpy as np
import trimesh
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 3)[0])
from badf.bench._cases import folded_sheet  # noqa: E402
from badf.bench._common import deform, find_mesh, start_warp, timestamp  # noqa: E402
from badf.server.adf import DistanceField, _bvh  # noqa: E402
from badf.server.adf._tolerances import FAT_AREA, SOUP_AREA, WINDING_BUDGET  # noqa: E402

SETTINGS = {"gated": (WINDING_BUDGET, SOUP_AREA, FAT_AREA), "every": (WINDING_BUDGET, SOUP_AREA, 0.0),
            "always": (WINDING_BUDGET, 0.0, 0.0), "fat-always": (WINDING_BUDGET, 0.0, FAT_AREA),
            "never": (2**30, float("inf"), 0.0)}


def thrown(vertices: np.ndarray, noise: float, fraction: float = 1.0) -> np.ndarray:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    rng = np.random.default_rng(0)
    throw = rng.uniform(-1.0, 1.0, size=vertices.shape) * noise * float(np.max(hi - lo))
    throw[rng.random(len(vertices)) >= fraction] = 0.0
    return np.clip(vertices + throw, lo, hi).astype(np.float32)


def sphere_areas(field: DistanceField) -> float:
    """The frame's area over the area of the sphere the BVH's root bounds, as the walks read it."""
    moments = field._bvh.node_moments.numpy()
    return float(moments[1][3] / (4.0 * np.pi * moments[0][3] ** 2))


def run_case(case: dict, setting: str, depth: int, device: str) -> dict:
    _bvh.WINDING_BUDGET, _bvh.SOUP_AREA, _bvh.FAT_AREA = SETTINGS[setting]
    vertices, faces = case["vertices"], case["faces"]
    field = DistanceField(vertices, faces, depth=depth, sign=case["sign"], device=device, rigid="off")
    calm = [deform(vertices, 0.02 * k) for k in range(1, 4)] if case["frame"] is not None else [vertices] * 3
    for frame in calm:
        field.update(frame)
    target = case["frame"] if case["frame"] is not None else vertices
    wp.synchronize_device(device)
    start = time.perf_counter()
    field.update(target)
    wp.synchronize_device(device)
    wall = time.perf_counter() - start
    stats = field.stats()
    positions, values, _ = field.corner_samples()
    row = {"case": case["name"], "setting": setting, "faces": len(faces), "wall_s": round(wall, 4),
           "winding_walks_cut": stats["winding_walks_cut"], "corners": stats["counts"]["unique_corners"],
           "sphere_areas": round(sphere_areas(field), 3), "values": values}
    if case["name"].startswith("cylinder"):
        inside = (np.hypot(positions[:, 0], positions[:, 1]) < 0.5) & (np.abs(positions[:, 2]) < 1.0)
        off = np.abs(values) > 1e-3 * float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
        row["sides_unlike_the_solid"] = int(np.sum(((values < 0) != inside) & off))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", default=["stanford-bunny"])
    parser.add_argument("--device", default=None)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--sections", type=int, default=2000)
    parser.add_argument("--layers", type=int, default=110)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.02, 0.05, 0.2])
    parser.add_argument("--fractions", type=float, nargs="+", default=[1.0])
    parser.add_argument("--fat-areas", type=float, nargs="*", default=[],
                        help="also run the gated budget with these values of FAT_AREA")
    parser.add_argument("--fat-always", action="store_true", help="also run the fat count with no soup gate")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    device = start_warp(args.device)
    settings = ["never", "gated", "every", "always"] + (["fat-always"] if args.fat_always else [])
    for fat_area in args.fat_areas:
        SETTINGS[f"fat={fat_area:g}"] = (WINDING_BUDGET, SOUP_AREA, fat_area)
        settings.append(f"fat={fat_area:g}")
    cylinder = trimesh.creation.cylinder(radius=0.5, height=2.0, sections=args.sections)
    cases = [{"name": f"cylinder {args.sections}", "sign": "winding", "frame": None,
              "vertices": np.asarray(cylinder.vertices, np.float32), "faces": np.asarray(cylinder.faces, np.int32)}]
    sheet_vertices, sheet_faces = folded_sheet(args.layers)
    cases.append({"name": f"folded sheet {args.layers}", "sign": "winding", "frame": None, "vertices": sheet_vertices,
                  "faces": sheet_faces})
    for mesh in args.meshes:
        data = np.load(find_mesh(mesh))
        vertices = data["vertices"][0] if data["vertices"].ndim == 3 else data["vertices"]
        vertices, faces = np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(data["faces"], np.int32)
        name = mesh.rsplit('/', 1)[-1].removesuffix('.npz')
        for noise in args.noise:
            for fraction in args.fractions:
                share = "" if fraction >= 1.0 else f" {fraction:.0%} of it"
                cases.append({"name": f"{name} thrown {noise:g}{share}", "sign": "auto",
                              "frame": thrown(vertices, noise, fraction), "vertices": vertices, "faces": faces})
    report = {"device": wp.get_device(device).name, "date": timestamp(), "depth": args.depth,
              "soup_area": SOUP_AREA, "budget": WINDING_BUDGET, "rows": []}
    for case in cases:
        reference = None
        for round_index in range(args.rounds):
            for setting in settings:
                row = run_case(case, setting, args.depth, device)
                values = row.pop("values")
                reference = values if reference is None else reference
                row["sides_unlike_never"] = int(np.sum((values < 0) != (reference < 0)))
                row["round"] = round_index
                report["rows"].append(row)
                print(json.dumps(row), flush=True)
    print(f"\n{report['device']}, {report['date']}, depth {args.depth}, budget {WINDING_BUDGET}, "
          f"soup at {SOUP_AREA:g} sphere areas, fat nodes at {FAT_AREA:g} disc areas:")
    width = max(len("case"), *(len(r["case"]) for r in report["rows"]))
    print(f"{'case':>{width}} {'setting':>8} {'areas':>7} {'wall s':>8} {'walks cut':>10} {'corners':>9} "
          f"{'sides unlike never':>19} {'unlike the solid':>17}")
    for r in report["rows"]:
        print(f"{r['case']:>{width}} {r['setting']:>8} {r['sphere_areas']:>7.2f} {r['wall_s']:>8.3f} "
              f"{r['winding_walks_cut']:>10} {r['corners']:>9} {r['sides_unlike_never']:>19} "
              f"{r.get('sides_unlike_the_solid', ''):>17}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
