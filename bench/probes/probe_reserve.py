"""Probe: planned frames that reserve the octree's scratch up front against frames that grow it stage by stage.

Since 2026-11-28 a planned frame takes its largest stage's scratch at once (`Octree._reserve_scratch`); before,
a planned first frame grew it at the radix tree's stage and again at the corner set's, each growth waiting for
the device. This alternates the two in one process (which goes first alternates too), so both meet the same
machine: each round builds a new object (its first frame), runs `--moves` frames that each move the domain, and
times 65,536 exact queries, whose code neither way touches (a check on the machine's drift). It prints medians
and quartiles of the engine's own stage clock (device time), by stage.

    python bench/probes/probe_reserve.py --mesh MESH.npz [MESH.npz ...] --depth 7 --rounds 30 [--out F.json]
"""

import json
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import alternating_parser, fmt_quartiles, quartiles  # noqa: E402


def main() -> None:
    parser = alternating_parser(__doc__)
    parser.add_argument("--moves", type=int, default=5)
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    from badf.server.adf import DistanceField
    from badf.server.adf._octree import Octree

    reserve = Octree._reserve_scratch
    ways = {"reserved": reserve, "grown": lambda self, face_count, *after: None}
    report = {"device": None, "depth": args.depth, "rounds": args.rounds, "moves": args.moves, "meshes": {}}
    for path in args.mesh:
        data = np.load(path)
        vertices, faces = data["vertices"], data["faces"]
        vertices = (vertices[0] if vertices.ndim == 3 else vertices).astype(np.float32)
        extent = vertices.max(axis=0) - vertices.min(axis=0)
        step = np.array([0.5 * float(extent.max()), 0.0, 0.0], np.float32)
        points = (vertices.min(axis=0) - 0.1 * extent
                  + np.random.default_rng(0).random((65536, 3)) * 1.2 * extent).astype(np.float32)
        samples = {way: {"build": [], "moving": [], "exact_ms": []} for way in ways}
        for round_ in range(args.rounds + 1):  # the first round compiles and warms up, and is not counted
            for way in (list(ways) if round_ % 2 == 0 else list(reversed(ways))):
                Octree._reserve_scratch = ways[way]
                field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
                report["device"] = field.device
                build = field.stats()["times_ms"]
                moving = []
                for k in range(1, args.moves + 1):
                    field.update(vertices + k * step)
                    moving.append(field.stats()["times_ms"])
                field.query(points, mode="exact")  # sizes the query buffers
                start = time.perf_counter()
                field.query(points, mode="exact")
                exact = (time.perf_counter() - start) * 1e3
                if round_ > 0:
                    samples[way]["build"].append(build)
                    samples[way]["moving"] += moving
                    samples[way]["exact_ms"].append(exact)
                del field
        Octree._reserve_scratch = reserve
        name = path.rsplit("/", 1)[-1]
        rows = {}
        print(f"{name}, depth {args.depth}, {args.rounds} rounds each way on {report['device']} (ms: median [p25, p75])")
        for way, got in samples.items():
            row = {kind: {s: quartiles([t.get(s, 0.0) for t in got[kind]]) for s in got[kind][0]}
                   for kind in ("build", "moving")}
            row["exact_wall_ms"] = quartiles(got["exact_ms"])
            rows[way] = row
            print(f"  {way:<9} build {fmt_quartiles(row['build']['total'])}  "
                  f"moving frame {fmt_quartiles(row['moving']['total'])}  "
                  f"exact queries (wall) {fmt_quartiles(row['exact_wall_ms'])}")
            for kind in ("build", "moving"):
                print(f"    {kind:<7} " + "  ".join(f"{s} {q[1]:.3f}" for s, q in row[kind].items() if s != "total"))
        report["meshes"][name] = rows
    if args.out:
        with open(args.out, "w") as out:
            json.dump(report, out, indent=1)


if __name__ == "__main__":
    main()
