"""Probe: a coherent update that keeps its corners for the next frame on the device, inside its own work (and graph),
against one that launches the keeping from the host once the frame's report is back.

Since 2026-11-28 a frame gathers its report on the device and queues the keeping there (`CornerField.queue_keep`),
to take effect only if the frame fitted its plan; before, the host waited for the report and then launched it,
and the update's span held that turnaround. This runs two objects of each mesh in one process, one each way
(the second with `queue_keep` turned off, so `keep_frame` launches it from the host as before), and alternates
their coherent updates (which goes first alternates too), so both meet the same machine. It prints medians and
quartiles of the engine's stage clock (device time: the update's whole span, and its stages) and of the wall time
of `update`. The fields are the same bit for bit either way, which it checks at the end.

    python bench/probes/probe_keep.py --mesh MESH.npz [MESH.npz ...] --depth 7 --rounds 200 [--out F.json]
"""

import json
import sys

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import alternating_parser, fmt_quartiles, quartiles  # noqa: E402


def main() -> None:
    parser = alternating_parser(__doc__)
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    from badf.server.adf import DistanceField

    report = {"device": None, "depth": args.depth, "rounds": args.rounds, "meshes": {}}
    for path in args.mesh:
        data = np.load(path)
        vertices = data["vertices"]
        vertices = (vertices[0] if vertices.ndim == 3 else vertices).astype(np.float32)
        fields = {way: DistanceField(vertices, data["faces"], depth=args.depth, device=args.device)
                  for way in ("device", "host")}
        fields["host"]._corners.queue_keep = lambda report, fits_at: False
        report["device"] = fields["device"].device
        samples = {way: {"total": [], "stages": [], "wall": []} for way in fields}
        warm = 10
        for k in range(1, warm + args.rounds + 1):
            frame = vertices * np.float32(1.0 + 1e-4 * (k % 50))  # coherent frames: the domain holds
            for way in (list(fields) if k % 2 == 0 else list(reversed(fields))):
                fields[way].update(frame)
                if k > warm:
                    stats = fields[way].stats()
                    times = stats["times_ms"]
                    samples[way]["total"].append(times["total"])
                    samples[way]["stages"].append(sum(t for s, t in times.items() if s != "total"))
                    samples[way]["wall"].append(stats["update_wall_ms"])
        a, b = (f.corner_samples() for f in fields.values())
        same = all(np.array_equal(x, y) for x, y in zip(a, b))
        name = path.rsplit("/", 1)[-1]
        rows = {way: {kind: quartiles(values) for kind, values in got.items()} for way, got in samples.items()}
        rows["same_field"] = bool(same)
        rows["graph_captures"] = {way: f.stats()["graph_captures"] for way, f in fields.items()}
        print(f"{name}, depth {args.depth}, {args.rounds} coherent updates each way on {report['device']} "
              f"(ms: median [p25, p75]); same field: {same}")
        for way in fields:
            r = rows[way]
            print(f"  keep on {way:<6} update span {fmt_quartiles(r['total'])}  sum of its stages "
                  f"{fmt_quartiles(r['stages'])}  wall {fmt_quartiles(r['wall'])}")
        report["meshes"][name] = rows
    if args.out:
        with open(args.out, "w") as out:
            json.dump(report, out, indent=1)


if __name__ == "__main__":
    main()
