"""Probe, not part of the product: an open mesh's corner sides from its holes' caps instead of a winding walk.

Winding numbers add over triangles. Close each hole of an open mesh S with a fan C of triangles (each boundary
loop's edges joined to the loop's centroid, wound against the loop, so S + C is closed and consistently oriented).
Then w_S(p) = w_{S+C}(p) - w_C(p). Where S + C is a simple closed surface, w_{S+C} is 1 inside and 0 outside, which
the pseudonormal of p's nearest point on S + C tells (cheap beside the corner searches: what a closed mesh's
sign costs), and w_C is a plain sum of solid angles over the caps, with no walk: one triangle per boundary edge, 223
for the bunny. The engine's winding walk (Barill et al.'s expansions) visits about 143 nodes a corner.

This probe measures, on the engine's own depth-7 corners of one coherent update:
- the walk the engine runs (the same arithmetic as `probe_winding_tiers._winding_at`, far field 2 radii), timed;
- the caps' solid-angle sum at every corner, timed (the part a fan adds to a pseudonormal-signed frame);
- the sides each gives (capped: w_{S+C} from the engine's pseudonormal sign of S + C by exact queries, which the
  engine would have from its searches), how many differ, and which of the two the float64 oracle
  (`bench/_oracle.winding_number`) agrees with at every differing corner and at a spread sample.

It does not test whether S + C is simple (a fan across a warped hole can cut the surface): an engine would need
that check, per frame for a deforming mesh, or fall back to the walk.

    python bench/probes/probe_capped_winding.py MESH.npz [MESH.npz ...] [--device cuda:0] [--repeat 20] [--out F.json]
"""

import argparse
import json
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
sys.path.insert(0, __file__.rsplit("/", 3)[0])
from probe_winding_tiers import _walk  # noqa: E402

from badf.bench._oracle import winding_number  # noqa: E402
from badf.server.adf import DistanceField  # noqa: E402
from badf.server.adf._distance import _lattice_point  # noqa: E402
from badf.server.adf._geometry import solid_angle_checked  # noqa: E402


@wp.kernel(enable_backward=False)
def _caps_winding_at(keys: wp.array(dtype=wp.int64), count: int, origin: wp.vec3, cell: float,
                     caps: wp.array(dtype=wp.vec3), cap_count: int, w_out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    if i >= count:
        return
    p = _lattice_point(keys[i], origin, cell)
    total = float(0.0)
    for t in range(cap_count):
        angle, cancelled = solid_angle_checked(p, caps[3 * t], caps[3 * t + 1], caps[3 * t + 2])
        total += angle
    w_out[i] = total / (4.0 * wp.pi)


@wp.kernel(enable_backward=False)
def _corner_points(keys: wp.array(dtype=wp.int64), origin: wp.vec3, cell: float, out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = _lattice_point(keys[i], origin, cell)


def boundary_caps(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(capped vertices, capped faces, boundary edge count) for a mesh whose boundary is simple loops; raises
    ValueError where a vertex starts two boundary edges (the loops would be ambiguous)."""
    # weld vertices at one position, so seams are not holes
    _, weld = np.unique(vertices, axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    f = weld[faces]
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    open_edges = directed[counts[inverse.reshape(-1)] == 1]
    if len(open_edges) == 0:
        return vertices, faces, 0
    starts, per_start = np.unique(open_edges[:, 0], return_counts=True)
    if np.any(per_start > 1):
        raise ValueError("a vertex starts two boundary edges")
    # a welded id's position: any original vertex that maps to it
    position = np.zeros((weld.max() + 1, 3), np.float64)
    position[weld] = vertices
    following = dict(zip(open_edges[:, 0].tolist(), open_edges[:, 1].tolist()))
    seen: set[int] = set()
    new_vertices, new_faces = [], []
    for start in following:
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        while following[loop[-1]] != start:
            loop.append(following[loop[-1]])
            seen.add(loop[-1])
        centre_id = len(position) + len(new_vertices)
        new_vertices.append(position[loop].mean(axis=0))
        for a, b in zip(loop, loop[1:] + loop[:1]):
            new_faces.append((b, a, centre_id))  # against the loop's edge a -> b, as the face beside it runs it
    capped_vertices = np.concatenate([position, np.asarray(new_vertices)]).astype(vertices.dtype)
    capped_faces = np.concatenate([f, np.asarray(new_faces)]).astype(np.int32)
    return capped_vertices, capped_faces, len(open_edges)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("meshes", nargs="+")
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--device", default=None)
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--sample", type=int, default=2000, help="corners also held to the oracle, spread evenly")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    wp.config.quiet = True
    report = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "depth": args.depth, "meshes": {}}
    for path in args.meshes:
        data = np.load(path)
        v = data["vertices"]
        v = (v[0] if v.ndim == 3 else v).astype(np.float32)
        f = data["faces"].astype(np.int32)
        capped_v, capped_f, boundary = boundary_caps(v, f)
        cap_faces = capped_f[len(f):]
        field = DistanceField(v, f, depth=args.depth, sign="winding", device=args.device)
        field.use_graphs = False
        field.update(v)  # a coherent frame, so the corners are an update's
        device = field._device
        report["device"] = wp.get_device(device).name if device.is_cuda else "cpu"
        domain, octree = field._domain, field._octree
        n = octree.corner_count
        cell = domain.local_side / (1 << field._depth)
        caps_local = domain.to_local(capped_v[cap_faces].reshape(-1, 3))
        caps = wp.array(caps_local, dtype=wp.vec3, device=device)
        w_caps = wp.zeros(n, dtype=wp.float32, device=device)

        def caps_launch():
            wp.launch(_caps_winding_at, dim=n, inputs=[octree.corner_keys, n, domain.origin, cell, caps,
                      len(cap_faces)], outputs=[w_caps], device=device)

        caps_launch()  # compile and warm
        caps_ms = []
        for _ in range(args.repeat if device.is_cuda else 1):
            if device.is_cuda:
                begin, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
                wp.record_event(begin)
            started = time.perf_counter()
            caps_launch()
            if device.is_cuda:
                wp.record_event(end)
                wp.synchronize_device(device)
                caps_ms.append(wp.get_event_elapsed_time(begin, end))
            else:
                caps_ms.append((time.perf_counter() - started) * 1e3)
        w_walk = wp.zeros(n, dtype=wp.float32, device=device)
        visits = wp.zeros(n, dtype=wp.int32, device=device)
        every = np.arange(n, dtype=np.int32)
        _walk(field, every, 2.0, w_walk, visits, 1)  # compile and warm
        walk_ms = _walk(field, every, 2.0, w_walk, visits, args.repeat)
        if not device.is_cuda:
            started = time.perf_counter()
            _walk(field, every, 2.0, w_walk, visits, 1)
            walk_ms = (time.perf_counter() - started) * 1e3

        local = wp.zeros(n, dtype=wp.vec3, device=device)
        wp.launch(_corner_points, dim=n, inputs=[octree.corner_keys, domain.origin, cell], outputs=[local],
                  device=device)
        points = local.numpy().astype(np.float64) / domain.scale + domain.centre
        closed = DistanceField(capped_v, capped_f, depth=args.depth, sign="pseudonormal", device=args.device)
        inside_closed = closed.query(points.astype(np.float32), mode="exact").distance < 0
        walk_side = np.abs(w_walk.numpy()) > 0.5
        capped_w = inside_closed.astype(np.float64) - w_caps.numpy()
        capped_side = np.abs(capped_w) > 0.5
        differ = np.flatnonzero(walk_side != capped_side)
        sample = np.unique(np.concatenate([differ, np.linspace(0, n - 1, min(args.sample, n)).astype(np.int64)]))
        truth = winding_number(points[sample], v.astype(np.float64), f)
        true_side = np.abs(truth) > 0.5
        at_differ = np.isin(sample, differ)
        row = {
            "triangles": len(f), "boundary_edges": boundary, "cap_triangles": len(cap_faces), "corners": n,
            "walk_ms": round(walk_ms, 4), "walk_visits_mean": round(float(visits.numpy().mean()), 1),
            "caps_ms_median": round(float(np.median(caps_ms)), 4),
            "sides_differ": len(differ),
            "differing_walk_right": int(np.sum(walk_side[sample][at_differ] == true_side[at_differ])),
            "differing_capped_right": int(np.sum(capped_side[sample][at_differ] == true_side[at_differ])),
            "sample": len(sample),
            "sample_walk_wrong": int(np.sum(walk_side[sample] != true_side)),
            "sample_capped_wrong": int(np.sum(capped_side[sample] != true_side)),
            "sample_walk_w_error_max": round(float(np.max(np.abs(w_walk.numpy()[sample] - truth))), 6),
            "sample_capped_w_error_max": round(float(np.max(np.abs(capped_w[sample] - truth))), 6),
        }
        name = path.rsplit("/", 1)[-1].removesuffix(".npz")
        report["meshes"][name] = row
        print(f"{name} ({report['device']}, depth {args.depth}): {row}", flush=True)
    print(f"\n{'mesh':<22}{'boundary':>9}{'corners':>9}{'walk ms':>9}{'caps ms':>9}{'differ':>8}{'walk err':>10}"
          f"{'caps err':>10}")
    for name, r in report["meshes"].items():
        print(f"{name:<22}{r['boundary_edges']:>9}{r['corners']:>9}{r['walk_ms']:>9.3f}{r['caps_ms_median']:>9.3f}"
              f"{r['sides_differ']:>8}{r['sample_walk_w_error_max']:>10.2e}{r['sample_capped_w_error_max']:>10.2e}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
