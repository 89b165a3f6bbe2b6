"""Would a BVH of better shape pay for itself frame after frame? The engine's BVH is Karras's radix tree over the
triangles' Morton codes, linked on the device at each build (registration, and a frame that moves the domain);
every other frame only refits its boxes, so a tree of better shape built once would serve every frame after.

This probe builds a top-down binned SAH tree on the host (numpy, one Python step per node: a probe, not an engine
build) and puts it in the engine's place: the same arrays (leaf order, children, leaf ranges), linked into the
4-wide view by the engine's own kernels. The leaves' keys are then in the SAH's order, not sorted, so a search
seeded by key (a first frame, coherence off) starts from some leaf: any leaf is a valid bound, so the answers
stay exact, and the coherent updates timed here are seeded by last frame's faces as usual.

Two objects per mesh, one on each tree, built alternately round by round; per round each takes three warm-up
updates and then `--frames` timed ones of the bench's wobble (no frame moves the domain, checked). Printed: the
median of each stage and of the wall time per tree, and the answers of both trees at the last frame (exact
distances must agree to the last bit; ADF distances and signs where the winding numbers' far-field terms, summed
over other clusters, land on either side of 1/2).

    python bench/probes/probe_sah_tree.py MESH.npz [MESH.npz ...] --device cuda:0 --rounds 4 --frames 20 --out F.json
"""

import argparse
import json
import sys
import time

import numpy as np
import warp as wp

from badf.bench._common import deform
from badf.server.adf import DistanceField, _bvh

BINS = 32
MAX_DEPTH = 62  # the binary tree's deepest level that the searches' stacks hold (_bvh.WIDE_STACK_DEPTH)


def sah_tree(vertices: np.ndarray, faces: np.ndarray):
    """A binned SAH tree over the triangles, leaf = one triangle, in the radix tree's layout: internal nodes
    0..n-2 (root 0), leaf k (the k-th triangle of `order`) as n - 1 + k, each node's leaves a range
    first..last of `order`. Returns (order, left, right, first, last, depth reached)."""
    tri = vertices[faces].astype(np.float64)
    lower, upper = tri.min(axis=1), tri.max(axis=1)
    centre = tri.mean(axis=1)
    n = len(faces)
    order = np.arange(n)
    left = np.empty(n - 1, np.int32)
    right = np.empty(n - 1, np.int32)
    first = np.empty(n - 1, np.int32)
    last = np.empty(n - 1, np.int32)
    next_id = 1
    deepest = 0
    stack = [(0, n, 0, 0)]  # (begin, end, node id, depth) of an internal node's range
    while stack:
        begin, end, node, depth = stack.pop()
        deepest = max(deepest, depth)
        count = end - begin
        first[node], last[node] = begin, end - 1
        split = begin + count // 2
        if count > 2 and depth < MAX_DEPTH - 8:
            ids = order[begin:end]
            c = centre[ids]
            lo, hi = c.min(axis=0), c.max(axis=0)
            axis = int(np.argmax(hi - lo))
            extent = hi[axis] - lo[axis]
            if extent > 0:
                bins = np.minimum((BINS * (c[:, axis] - lo[axis]) / extent).astype(np.int64), BINS - 1)
                sorted_ids = np.argsort(bins, kind="stable")
                counts = np.bincount(bins, minlength=BINS)
                used = np.nonzero(counts)[0]
                starts = np.concatenate([[0], np.cumsum(counts[used])[:-1]])
                b_lo = np.minimum.reduceat(lower[ids[sorted_ids]], starts, axis=0)
                b_hi = np.maximum.reduceat(upper[ids[sorted_ids]], starts, axis=0)
                l_lo, l_hi = np.minimum.accumulate(b_lo), np.maximum.accumulate(b_hi)
                r_lo = np.minimum.accumulate(b_lo[::-1])[::-1]
                r_hi = np.maximum.accumulate(b_hi[::-1])[::-1]
                on_left = np.cumsum(counts[used])

                def area(a, b):
                    d = b - a
                    return d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0]

                cost = area(l_lo[:-1], l_hi[:-1]) * on_left[:-1] + area(r_lo[1:], r_hi[1:]) * (count - on_left[:-1])
                if len(cost):
                    order[begin:end] = ids[sorted_ids]
                    split = begin + int(on_left[int(np.argmin(cost))])
        children = []
        for lo_, hi_ in ((begin, split), (split, end)):
            if hi_ - lo_ == 1:
                children.append(n - 1 + lo_)
            else:
                children.append(next_id)
                stack.append((lo_, hi_, next_id, depth + 1))
                next_id += 1
        left[node], right[node] = children
    return order.astype(np.int32), left, right, first, last, deepest + 1


USE_SAH = False
SAH_BUILD_S: list[float] = []
_engine_build = _bvh.Bvh.build


def _build(self, vertices, faces, origin, side):
    """The engine's build, then (when USE_SAH) the SAH tree in the radix tree's place."""
    _engine_build(self, vertices, faces, origin, side)
    n = self.face_count
    if not USE_SAH or n < 3:
        return
    started = time.perf_counter()
    order, left, right, first, last, _ = sah_tree(vertices.numpy(), faces.numpy())
    SAH_BUILD_S.append(time.perf_counter() - started)
    keys = self.leaf_key.numpy()
    faces_sorted = self.leaf_face.numpy()
    key_of_face = np.empty(n, np.int64)
    key_of_face[faces_sorted] = keys
    self.leaf_face.assign(order)
    self.leaf_key.assign(key_of_face[order])  # unsorted: a seed by key is some leaf (a valid bound)
    wp.launch(_bvh._invert_order, dim=n, inputs=[self.leaf_face], outputs=[self.face_leaf], device=self.device)
    b = self._buffers
    arrays = {name: b.ensure(f"bvh.build.{name}", n - 1, wp.int32) for name in ("left", "right", "first", "last")}
    for name, values in zip(("left", "right", "first", "last"), (left, right, first, last)):
        arrays[name].assign(values)
    slot_first = b.ensure("bvh.build.slot_first", 2 * (n - 1), wp.int32)
    slot_count = b.ensure("bvh.build.slot_count", 2 * (n - 1), wp.int32)
    parent_slot = b.ensure("bvh.build.parent_slot", 2 * n - 1, wp.int32)
    parent_slot.fill_(-1)
    wp.launch(_bvh._link_slots, dim=n - 1,
              inputs=[arrays["left"], arrays["right"], arrays["first"], arrays["last"], n - 1],
              outputs=[self.slot_child, slot_first, slot_count, parent_slot], device=self.device)
    self.wide.link(self.slot_child, slot_count, slot_first, parent_slot, arrays["left"], arrays["right"])
    self._cuts.clear()


_bvh.Bvh.build = _build


def make(vertices, faces, device, name: str) -> DistanceField:
    """radix: the engine's Morton tree; sah: this probe's SAH tree linked in its place; engine-sah: bvh="sah"."""
    global USE_SAH
    USE_SAH = name == "sah"
    try:
        return DistanceField(vertices, faces, depth=7, device=device, bvh="sah" if name == "engine-sah" else "morton")
    finally:
        USE_SAH = False


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="+")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--out")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    print(f"{wp.get_device(args.device).name}, warp {wp.__version__}, {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}")
    report = {"device": wp.get_device(args.device).name, "warp": wp.__version__, "meshes": {}}
    for path in args.meshes:
        data = np.load(path)
        vertices, faces = np.asarray(data["vertices"], np.float32), np.asarray(data["faces"], np.int32)
        order, *_, depth = sah_tree(vertices, faces)
        names = ("radix", "sah", "engine-sah")
        times = {name: {} for name in names}
        walls = {name: [] for name in names}
        fields = {}
        frame = 0
        for round_ in range(args.rounds):
            for name in (names if round_ % 2 == 0 else names[::-1]):
                field = fields.get(name) or make(vertices, faces, args.device, name)
                fields[name] = field
                for k in range(3):
                    field.update(deform(vertices, 0.05 * (frame + k)))
                for k in range(args.frames):
                    moved = deform(vertices, 0.05 * (frame + 3 + k))
                    started = time.perf_counter()
                    field.update(moved)
                    walls[name].append((time.perf_counter() - started) * 1e3)
                    for stage, ms in field.stats()["times_ms"].items():
                        times[name].setdefault(stage, []).append(ms)
            frame += 3 + args.frames
        last = deform(vertices, 0.05 * (frame + 1))
        rng = np.random.default_rng(7)
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        points = (lo + (hi - lo) * rng.uniform(-0.1, 1.1, size=(20000, 3))).astype(np.float32)
        answers = {}
        for name, field in fields.items():
            field.update(last)
            exact = field.query(points, mode="exact").distance
            adf = field.query(points, mode="adf").distance
            answers[name] = (exact, adf)
            assert field.stats()["domain_moves"] == 0, "a frame moved the domain: the SAH tree was rebuilt"
        (ea, aa), (eb, ab) = answers["radix"], answers["sah"]
        row = {
            "triangles": len(faces), "sah_depth": depth, "sah_build_s_host": SAH_BUILD_S[-1],
            "median_ms": {name: {stage: float(np.median(v)) for stage, v in times[name].items()} for name in times},
            "wall_median_ms": {name: float(np.median(v)) for name, v in walls.items()},
            "exact_max_abs_difference": float(np.max(np.abs(np.abs(ea) - np.abs(eb)))),
            "exact_sign_differences": int(np.sum(np.sign(ea) != np.sign(eb))),
            "adf_max_abs_difference_of_magnitudes": float(np.max(np.abs(np.abs(aa) - np.abs(ab)))),
            "adf_sign_differences": int(np.sum(np.sign(aa) != np.sign(ab))),
        }
        report["meshes"][path] = row
        print(f"\n{path}: {len(faces)} triangles, SAH tree {depth} levels, its host build {SAH_BUILD_S[-1]:.2f} s")
        stages = list(row["median_ms"]["radix"])
        print(f"{'stage':>14}" + "".join(f" {name:>10}" for name in names))
        for stage in stages:
            print(f"{stage:>14}" + "".join(f" {row['median_ms'][name].get(stage, float('nan')):10.3f}" for name in names))
        print(f"{'wall':>14}" + "".join(f" {row['wall_median_ms'][name]:10.3f}" for name in names))
        print(f"answers at 20,000 points: exact |d| max difference {row['exact_max_abs_difference']:.3g}, "
              f"signs differing {row['exact_sign_differences']}; adf |d| {row['adf_max_abs_difference_of_magnitudes']:.3g}, "
              f"signs differing {row['adf_sign_differences']}")
        sys.stdout.flush()
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
