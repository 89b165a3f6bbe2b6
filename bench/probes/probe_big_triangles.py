"""Build and update times of meshes whose triangles are much larger than a finest cell: a tilted square of
two triangles (a floor or a CAD face at an angle to every axis), an axis-aligned one, and a box of 12
triangles. The surface-cell stage tests the cells of each triangle's bounding box, so the work of one
triangle grows with its size in cells. Each case runs in a child process under a time limit, so a stage
that takes far too long shows as a timeout instead of holding the run.

    python3 bench/probes/probe_big_triangles.py --device cuda:0 --depths 6 7 8 9 10 --limit 120
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

CASES = ("tilted-square", "flat-square", "box")


def mesh(case: str) -> tuple[np.ndarray, np.ndarray]:
    if case == "box":
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
        faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                          [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        return corners, faces
    if case == "flat-square":
        u, v = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    else:  # its normal is (1, 1, 1) / sqrt(3): oblique to every axis
        u, v = np.array([1.0, -1.0, 0.0]) / np.sqrt(2), np.array([1.0, 1.0, -2.0]) / np.sqrt(6)
    return np.array([-u - v, u - v, u + v, -u + v]), np.array([[0, 1, 2], [0, 2, 3]])


def one(case: str, depth: int, device: str) -> dict:
    from badf.server.adf import DistanceField

    vertices, faces = mesh(case)
    started = time.perf_counter()
    field = DistanceField(vertices, faces, depth=depth, device=device, sign="none" if "square" in case else "auto")
    build_s = time.perf_counter() - started
    stats = field.stats()
    started = time.perf_counter()
    field.update(vertices * 1.001)
    update_s = time.perf_counter() - started
    return {"case": case, "depth": depth, "build_s": build_s, "update_s": update_s,
            "build_surface_cells_ms": stats["times_ms"]["surface_cells"],
            "update_surface_cells_ms": field.stats()["times_ms"]["surface_cells"],
            "surface_cells": stats["counts"]["surface_cells"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--depths", type=int, nargs="+", default=[6, 7, 8])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--limit", type=float, default=120.0, help="seconds per case and depth")
    parser.add_argument("--one", nargs=2, metavar=("CASE", "DEPTH"), help=argparse.SUPPRESS)
    parser.add_argument("--out")
    args = parser.parse_args()
    if args.one:
        print(json.dumps(one(args.one[0], int(args.one[1]), args.device)))
        return
    rows = []
    print(f"{'case':>14} {'depth':>5} {'build s':>9} {'update s':>9} {'surface ms (build/update)':>26} {'cells':>9}")
    for case in args.cases:
        for depth in args.depths:
            command = [sys.executable, __file__, "--device", args.device, "--one", case, str(depth)]
            try:
                done = subprocess.run(command, capture_output=True, text=True, timeout=args.limit)
            except subprocess.TimeoutExpired:
                rows.append({"case": case, "depth": depth, "timed_out_s": args.limit})
                print(f"{case:>14} {depth:>5}   over the {args.limit:.0f} s limit", flush=True)
                continue
            if done.returncode != 0:
                rows.append({"case": case, "depth": depth, "error": done.stderr[-500:]})
                print(f"{case:>14} {depth:>5}   failed: {done.stderr.strip().splitlines()[-1]}", flush=True)
                continue
            row = json.loads(done.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"{case:>14} {depth:>5} {row['build_s']:9.3f} {row['update_s']:9.3f} "
                  f"{row['build_surface_cells_ms']:12.2f} / {row['update_surface_cells_ms']:10.2f} "
                  f"{row['surface_cells']:9d}", flush=True)
    if args.out:
        with open(args.out, "w") as file:
            json.dump({"device": args.device, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                       "rows": rows}, file, indent=1)


if __name__ == "__main__":
    main()
