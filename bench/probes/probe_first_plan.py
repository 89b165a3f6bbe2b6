"""Probe: a build whose first frame is planned from the surface's area against one that measures its sizes.

A measured frame reads four sizes back on the way and waits on the device each time; a planned one reads
nothing until its end. Since 2026-11-28 the first frame is planned from an estimate (`Octree.plan_first_frame`)
where it can be. This builds each mesh `--rounds` times each way, alternating in one process (which way goes
first alternates too), so both meet the same machine, and prints the medians and quartiles of the build's
device time (the engine's own stage clock) by stage, and of its wall time.

    python bench/probes/probe_first_plan.py --mesh MESH.npz [MESH.npz ...] --depth 7 --rounds 30 [--out F.json]
"""

import json
import sys

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import alternating_parser, fmt_quartiles, quartiles  # noqa: E402


def main() -> None:
    parser = alternating_parser(__doc__)
    args = parser.parse_args()

    import time

    import warp as wp

    wp.config.quiet = True
    from badf.server.adf import DistanceField
    from badf.server.adf._octree import Octree

    estimate = Octree.plan_first_frame
    ways = {"planned": estimate, "measured": lambda self, face_count, side: False}
    report = {"device": None, "depth": args.depth, "rounds": args.rounds, "meshes": {}}
    for path in args.mesh:
        data = np.load(path)
        vertices, faces = data["vertices"], data["faces"]
        vertices = vertices[0] if vertices.ndim == 3 else vertices
        samples = {way: {"stages": [], "wall": [], "measured_frames": []} for way in ways}
        for round_ in range(args.rounds + 1):  # the first round compiles and warms up, and is not counted
            order = list(ways) if round_ % 2 == 0 else list(reversed(ways))
            for way in order:
                Octree.plan_first_frame = ways[way]
                start = time.perf_counter()
                field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
                wall = (time.perf_counter() - start) * 1e3
                stats = field.stats()
                report["device"] = field.device
                if round_ > 0:
                    samples[way]["stages"].append(stats["times_ms"])
                    samples[way]["wall"].append(wall)
                    samples[way]["measured_frames"].append(stats["measured_frames"])
                del field
        Octree.plan_first_frame = estimate
        name = path.rsplit("/", 1)[-1]
        rows = {}
        print(f"{name}, depth {args.depth}, {args.rounds} builds each way on {report['device']} (ms: median [p25, p75])")
        for way, got in samples.items():
            stage_names = got["stages"][0].keys()
            row = {s: quartiles([t.get(s, 0.0) for t in got["stages"]]) for s in stage_names}
            row["wall"] = quartiles(got["wall"])
            row["measured_frames"] = sorted(set(got["measured_frames"]))
            rows[way] = row
            print(f"  {way:<9} total {fmt_quartiles(row['total'])}  wall {fmt_quartiles(row['wall'])}  "
                  f"measured frames {row['measured_frames']}")
            print("            " + "  ".join(f"{s} {row[s][1]:.3f}" for s in stage_names if s != "total"))
        report["meshes"][name] = rows
    if args.out:
        with open(args.out, "w") as out:
            json.dump(report, out, indent=1)


if __name__ == "__main__":
    main()
