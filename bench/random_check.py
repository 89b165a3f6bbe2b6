"""Random check: random meshes, options and frames against the float64 oracle, for a bounded time or count.

    badf bench random-check [--seconds 300] [--cases N] [--seed 0] [--depths 3 6] [--device cpu] [--out check.json]

Each case is drawn from its seed alone: a mesh (a piece of a shared mesh, a noisy or holed sphere, a soup with
repeated corners, a sphere with duplicated and flipped faces, a folded sheet, a sphere scaled and moved far from
the origin; since 2026-12-08 also a hollow shell, a box with a fin (an edge of three faces), a sphere with slivers
and triangles of no area, a wide box beside a tiny sphere, two crossing spheres, a sphere with unused vertices far
away, a torus, a box 1e-6 to 1e-2 thick, a sphere given twice, and a cone of up to 2,000 needles), options (depth 3 to 6, or as `--depths` says, every sign method, refinement, halo, coherence, now and
then a band, a region or the SAH-shaped BVH) and up to three frames (a wobble, jitter from 1e-6 to 0.1 of the
size, a throw of up to 1000 sizes, a collapse onto a plane, a scaling, or the same frame again), with float32 or
float64 input, and far corners searched by subtree (CornerField.far_cells, which only CUDA chooses on its own) or
not. A refused mesh or frame (InvalidInputError)
is an outcome, not a problem. A slice through the mesh (24 x 24) must be finite and list only cells its plane
crosses. Then 180 points (uniform in the domain, near and on the surface, and 50 diagonals
away) are answered in both modes and compared with the oracle, within the bounds of the stability table
(`_cases.compare_with_oracle`); points beyond a band are left out (their answers are clamped by design), and the
signs of pseudonormals forced on a mesh are not counted (an open or self-intersecting one is documented to
disagree), nor are the sides of points whose winding-number walk was cut at its budget (a crumpled frame's soup, where
the engine documents the side as an estimate and counts the cut walks): such cases are counted apart
(`signs_estimated`). A problem is any other exception, a non-finite answer, or an answer outside its bound; each is
printed with its seed, which reproduces it.

On 2026-11-29 the script this was made from ran 4,834 cases on the CPU back-end (15 minutes) and found nothing; on
an H200 it found an illegal address (the far corners' list, docs/hardening.md), and after the fix 403 cases (212
s) found nothing. This module, which also draws the far-corner threshold and regions and checks a slice: 553 cases
on the CPU in 120 s, none.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import time
import traceback

import numpy as np

from badf.bench import _cases
from badf.bench import _oracle as oracle
from badf.bench._common import BenchFlagError, bench_device_name, start_warp, timestamp

MESH_KINDS = ("shared piece", "noisy sphere", "soup", "holed sphere", "duplicates", "folded sheet", "far sphere",
              "hollow shell", "fin", "slivers", "mixed sizes", "overlapping spheres", "unused vertices", "torus",
              "thin plate", "double cover", "needle fan")
MOTIONS = ("wobble", "jitter", "throw", "collapse", "scale", "same")
SHARED_MESHES = ("spot", "fandisk", "stanford-bunny", "homer", "armadillo-86k")
DEPTHS = (3, 6)  # the octree depths drawn from, both included (--depths)
POINTS = 60  # of each kind: uniform, near the surface, on it (half), and eight far away


def shared_meshes(names=SHARED_MESHES) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The shared meshes beside this checkout, by name (those missing are left out)."""
    found = {}
    for name in names:
        try:
            found[name] = _cases.shared_mesh(name)
        except FileNotFoundError:
            pass
    return found


def random_mesh(rng: np.random.Generator, shared: dict) -> tuple[str, np.ndarray, np.ndarray]:
    """(kind, vertices float64, faces) of one of MESH_KINDS; three in ten of the kinds built here are then scaled by
    1e-4 to 1e4 and moved up to 1e5 from the origin."""
    kinds = MESH_KINDS if shared else MESH_KINDS[1:]
    kind = str(rng.choice(kinds))
    if kind == "shared piece":
        vertices, faces = shared[str(rng.choice(sorted(shared)))]
        count = int(rng.integers(20, len(faces) + 1))
        first = int(rng.integers(0, len(faces) - count + 1))
        faces = faces[first : first + count]
    elif kind == "soup":
        n = int(rng.integers(1, 300))
        vertices = rng.normal(size=(3 * n, 3))
        faces = np.arange(3 * n).reshape(n, 3)
        repeated = np.flatnonzero(rng.random(n) < 0.1)
        vertices[3 * repeated + 1] = vertices[3 * repeated]
    elif kind == "folded sheet":
        m = int(rng.integers(2, 20))
        x, y = np.meshgrid(np.linspace(0, 1, m), np.linspace(0, 1, m))
        fold = x > 0.5
        z = np.where(fold, (x - 0.5) * rng.uniform(-1, 1), 0.0)
        vertices = np.stack([np.where(fold, 1 - x, x) * rng.uniform(0.5, 2), y, z], axis=-1).reshape(-1, 3)
        grid = np.arange(m * m).reshape(m, m)
        a, b, c, d = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel(), grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
        faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    elif kind in _SOLIDS:
        vertices, faces = _SOLIDS[kind](rng)
        if rng.random() < 0.3:
            vertices = vertices * 10.0 ** rng.uniform(-4, 4) + 10.0 ** rng.uniform(0, 5) * rng.normal(size=3)
    else:
        vertices, faces = _cases.icosphere(int(rng.integers(1, 4)))
        vertices = vertices * (1 + rng.normal(scale=float(rng.choice([0.0, 0.01, 0.2])), size=vertices.shape))
        if kind == "holed sphere":
            faces = faces[rng.random(len(faces)) > rng.uniform(0.01, 0.5)]
        elif kind == "duplicates":
            extra = faces[rng.integers(0, len(faces), size=int(rng.integers(1, 20)))]
            flip = rng.random(len(extra)) < 0.5
            extra[flip] = extra[flip][:, [0, 2, 1]]
            faces = np.concatenate([faces, extra])
        elif kind == "far sphere":
            vertices = vertices * 10.0 ** rng.uniform(-3, 5) + 10.0 ** rng.uniform(0, 6) * rng.normal(size=3)
    if len(faces) == 0:
        faces = np.array([[0, 1, 2]])
    return kind, np.asarray(vertices, np.float64), np.asarray(faces, np.int64)


def _sphere(rng: np.random.Generator, radius: float = 1.0, centre=(0.0, 0.0, 0.0), most: int = 3):
    vertices, faces = _cases.icosphere(int(rng.integers(1, most + 1)))
    return vertices * radius + np.asarray(centre, np.float64), faces.astype(np.int64)


def _joined(*parts: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """One mesh of several (vertices, faces), each part's faces renumbered after the vertices before it."""
    starts = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return (np.concatenate([v for v, _ in parts]),
            np.concatenate([f + start for (_, f), start in zip(parts, starts)]))


def _box(extents, subdivide: bool = False) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    box = trimesh.creation.box(extents=extents)
    box = box.subdivide() if subdivide else box
    return np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)


def _hollow_shell(rng):
    """A sphere with a smaller one inside, turned inward: a closed solid with a cavity (the cavity is outside)."""
    inner_v, inner_f = _sphere(rng, radius=rng.uniform(0.2, 0.95), most=2)
    return _joined(_sphere(rng), (inner_v, inner_f[:, [0, 2, 1]]))


def _fin(rng):
    """A box with one more triangle on one of its edges: an edge of three faces (not a manifold)."""
    vertices, faces = _box(rng.uniform(0.2, 2.0, 3))
    edge = faces[int(rng.integers(0, len(faces)))][:2]
    tip = vertices[edge].mean(axis=0) + rng.normal(size=3)
    return np.vstack([vertices, tip]), np.vstack([faces, [[edge[0], edge[1], len(vertices)]]])


def _slivers(rng):
    """A sphere with a few corners moved onto (or within 1e-7 or 1e-4 of) their triangle's opposite edge: triangles of
    no area, and needles."""
    vertices, faces = _sphere(rng)
    for a, b, c in faces[rng.integers(0, len(faces), size=int(rng.integers(1, 10)))]:
        s = rng.uniform(0.0, 1.0)
        vertices[a] = s * vertices[b] + (1 - s) * vertices[c] + float(rng.choice([0.0, 1e-7, 1e-4])) * rng.normal(size=3)
    return vertices, faces


def _mixed_sizes(rng):
    """A wide flat box (10 x 10 x 0.1) and a sphere 1e-4 to 1e-1 across beside it: triangles of very different sizes."""
    small = _sphere(rng, radius=10.0 ** rng.uniform(-4, -1), centre=rng.uniform(-1, 1, 3), most=2)
    return _joined(_box([10.0, 10.0, 0.1]), small)


def _overlapping_spheres(rng):
    """Two spheres that cross each other: a closed mesh whose parts intersect."""
    return _joined(_sphere(rng, most=2), _sphere(rng, radius=rng.uniform(0.5, 1.2), centre=(rng.uniform(0.1, 1.5), 0, 0),
                                                 most=2))


def _unused_vertices(rng):
    """A sphere with vertices no face uses, up to 1e6 away."""
    vertices, faces = _sphere(rng, most=2)
    extra = rng.normal(size=(int(rng.integers(1, 20)), 3)) * 10.0 ** rng.uniform(0, 6)
    return np.vstack([vertices, extra]), faces


def _torus(rng):
    import trimesh

    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=float(rng.uniform(0.01, 0.9)),
                                   major_sections=int(rng.integers(8, 64)), minor_sections=int(rng.integers(4, 32)))
    return np.asarray(torus.vertices, np.float64), np.asarray(torus.faces, np.int64)


def _thin_plate(rng):
    """A closed box 1e-6 to 1e-2 thick, its two sides far closer than a cell."""
    return _box([1.0, 1.0, 10.0 ** rng.uniform(-6, -2)], subdivide=bool(rng.random() < 0.5))


def _double_cover(rng):
    """A sphere given twice, face for face (winding number 2 inside)."""
    sphere = _sphere(rng, most=2)
    return _joined(sphere, sphere)


def _needle_fan(rng):
    """A cone of 3 to 2,000 needles around its tip, closed by a fan of as many around the base's centre."""
    n = int(rng.integers(3, 2000))
    angle = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    rim = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)
    vertices = np.vstack([rim, [[0.0, 0.0, rng.uniform(0.01, 3.0)]], [[0.0, 0.0, 0.0]]])
    i, j = np.arange(n), (np.arange(n) + 1) % n
    faces = np.concatenate([np.stack([i, j, np.full(n, n)], 1), np.stack([j, i, np.full(n, n + 1)], 1)])
    return vertices, faces


_SOLIDS = {"hollow shell": _hollow_shell, "fin": _fin, "slivers": _slivers, "mixed sizes": _mixed_sizes,
           "overlapping spheres": _overlapping_spheres, "unused vertices": _unused_vertices, "torus": _torus,
           "thin plate": _thin_plate, "double cover": _double_cover, "needle fan": _needle_fan}


def random_motion(vertices: np.ndarray, rng: np.random.Generator) -> tuple[str, np.ndarray]:
    """(name, the next frame) of one of MOTIONS."""
    how = str(rng.choice(MOTIONS))
    size = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0))) or 1.0
    if how == "wobble":
        return how, vertices + 0.01 * size * np.sin(vertices / size * 6.0 + rng.uniform(0, 6))
    if how == "jitter":
        return how, vertices + rng.normal(scale=size * float(rng.choice([1e-6, 1e-3, 0.1])), size=vertices.shape)
    if how == "throw":
        return how, vertices + rng.normal(size=3) * size * float(rng.choice([0.1, 3.0, 1000.0]))
    if how == "collapse":
        flat = vertices.copy()
        flat[:, int(rng.integers(0, 3))] = flat[:, 0].mean()
        return how, flat
    if how == "scale":
        centre = vertices.mean(axis=0)
        return how, centre + (vertices - centre) * float(rng.choice([1e-3, 0.5, 2.0, 100.0]))
    return how, vertices.copy()


# CornerField.far_cells for a case: the engine's choice (CUDA: 12 where no winding numbers run beside the searches,
# else 0), or far corners searched by subtree from 2 or 12 finest cells on any device, the CPU back-end included
FAR_CELLS = (None, None, 0, 2, 12)


def random_options(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, depths: tuple[int, int] = DEPTHS) -> dict:
    """The field's options for a mesh within [lo, hi]: a band in a quarter of cases, a region (a box within or
    across the mesh's bounds) in a fifth, each of the BVH's shapes asked for in three tenths (auto's in the rest)."""
    size = float(np.linalg.norm(hi - lo))
    depth = int(rng.integers(depths[0], depths[1] + 1))
    sign = str(rng.choice(["auto", "auto", "winding", "none", "pseudonormal"]))
    options = dict(depth=depth, sign=sign,
                   refine=str(rng.choice(["surface", "centroid"])), halo=int(rng.integers(0, 3)),
                   coherence=bool(rng.random() < 0.8))
    if rng.random() < 0.25:
        options["band"] = float(size * rng.uniform(0.01, 0.5))
    if rng.random() < 0.2:
        corners = lo + (hi - lo) * rng.uniform(-0.2, 1.2, size=(2, 3))
        options["region"] = np.sort(corners, axis=0).tolist()
    shape = rng.random()
    if shape < 0.6:  # else auto: sah on the CPU, morton on CUDA
        options["bvh"] = "sah" if shape < 0.3 else "morton"
    return options


@contextlib.contextmanager
def far_cells(value: int | None):
    """CornerField.far_cells set for the fields made within (their first frames run in the constructor)."""
    from badf.server.adf._distance import CornerField

    before = CornerField.far_cells
    CornerField.far_cells = value
    try:
        yield
    finally:
        CornerField.far_cells = before


def slice_trouble(field, vertices: np.ndarray, rng: np.random.Generator) -> str | None:
    """What is wrong with a slice through the mesh's bounds (a 24 x 24 grid on a random axis), if anything: a
    distance not finite, or a cell listed that the plane does not cross (float32's rounding, in the domain's units,
    allowed: a mesh collapsed onto a plane at -2.6e-18 lies on cells' faces at 0)."""
    axis = int(rng.integers(0, 3))
    lo, hi = vertices[:, axis].min(), vertices[:, axis].max()
    position = float(lo + (hi - lo) * rng.random())
    cut = field.slice(axis, position, resolution=24)
    if not np.all(np.isfinite(cut.distance)):
        return "a slice's distance is not finite"
    slack = 1e-6 * max(abs(position), float(field.info()["domain"]["side"]))  # float32 in the domain's units
    lower, upper = cut.cell_lower[:, axis].astype(np.float64), cut.cell_upper[:, axis].astype(np.float64)
    if np.any((lower > position + slack) | (upper < position - slack)):
        return "a slice lists a cell the plane does not cross"
    return None


def check_case(seed: int, device: str, shared: dict, depths: tuple[int, int] = DEPTHS) -> dict:
    """Draw case `seed`, run it, and compare with the oracle: its record, with "problem" set where it failed."""
    rng = np.random.default_rng(seed)
    kind, vertices, faces = random_mesh(rng, shared)
    options = random_options(rng, vertices.min(axis=0), vertices.max(axis=0), depths)
    frames = [random_motion(vertices, rng) for _ in range(int(rng.integers(0, 4)))]
    given = vertices.astype(rng.choice([np.float32, np.float64]))
    far = FAR_CELLS[int(rng.integers(0, len(FAR_CELLS)))]
    record = {"seed": seed, "mesh": kind, "faces": len(faces), "input": given.dtype.name, "options": options,
              "far_cells": far, "frames": [how for how, _ in frames]}
    with far_cells(far):
        return _run_case(record, given, faces, options, frames, device)


def _run_case(record: dict, given: np.ndarray, faces: np.ndarray, options: dict, frames: list, device: str) -> dict:
    from badf.server.adf import DistanceField, InvalidInputError

    seed = record["seed"]
    try:
        try:
            field = DistanceField(given, faces, device=device, **options)
        except InvalidInputError as refused:
            record["refused"] = str(refused)[:200]
            return record
        last = given.astype(np.float64)  # the oracle sees what the field was given
        for _, frame in frames:
            try:
                field.update(frame)
                last = frame
            except InvalidInputError as refused:
                record.setdefault("frames_refused", []).append(str(refused)[:200])
        trouble = slice_trouble(field, last, np.random.default_rng(seed))
        if trouble:
            record["problem"] = trouble
            return record
        points = _cases.probe_points(field, last, faces, POINTS, np.random.default_rng(seed))
        if "band" in options:  # answers beyond the band are clamped by design
            truth = oracle.nearest(points, last, faces).distance
            points = points[truth < 0.9 * options["band"]]
        if len(points) == 0:
            return record
        numbers = _cases.compare_with_oracle(field, last, faces, points, solid=False)
        if options["sign"] == "pseudonormal":
            numbers["wrong_signs"] = 0  # forced on an open or self-intersecting mesh they disagree, as documented
        elif numbers["wrong_signs"]:
            estimated = signs_estimated(field, last, faces, points)
            numbers["wrong_signs"] -= len(estimated)
            record["signs_estimated"] = len(estimated)
        outcome = _cases._verdict(numbers)
        record["measured"] = outcome.measured
        if not outcome.passed:
            record["problem"] = "answers outside their bounds"
    except Exception as error:  # noqa: BLE001 - any other exception is what this check looks for
        record["problem"] = repr(error)[:300]
        record["trace"] = traceback.format_exc()[-1500:]
    return record


def signs_estimated(field, vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> list[int]:
    """Of the points on the other side from the oracle's, those whose winding-number walk was cut at the budget
    (`WINDING_BUDGET`): a crumpled frame's soup of crossing faces, where the engine documents the sign as an
    estimate and counts the cut walks in `stats()["last_query_walks_cut"]`. Each is asked alone to tell whose
    walk it was. Before this, every such case read as a problem (12 of 5,689 cases on the CPU, 2026-12-07)."""
    cut = []
    for index in _cases.wrong_sides(field, vertices, faces, points):
        field.query(points[index : index + 1], mode="exact")
        if field.stats()["last_query_walks_cut"] > 0:
            cut.append(int(index))
    return cut


def check(*, seconds: float, cases: int | None, seed: int, device: str, depths: tuple[int, int] = DEPTHS) -> dict:
    """Cases seed, seed + 1, ... until `seconds` have passed or `cases` have run: counts and the problems found."""
    shared = shared_meshes()
    # the engine's warning for every case that forces pseudonormals on an open mesh says nothing new here
    logging.getLogger("badf.server").setLevel(logging.ERROR)
    start = time.perf_counter()
    records, n, compared, refused, estimated = [], 0, 0, 0, 0
    while time.perf_counter() - start < seconds and (cases is None or n < cases):
        record = check_case(seed + n, device, shared, depths)
        n += 1
        compared += "measured" in record
        refused += "refused" in record
        estimated += "signs_estimated" in record
        if "problem" in record:
            records.append(record)
            print("problem:", json.dumps(record), flush=True)
    return {"benchmark": "random_check", "date": timestamp(), "device": bench_device_name(device),
            "first_seed": seed, "depths": list(depths), "cases": n, "compared": compared, "refused": refused,
            "cases_with_signs_estimated": estimated,
            "seconds": round(time.perf_counter() - start, 1), "shared_meshes": sorted(shared), "problems": records}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=300.0, help="stop after this long (300)")
    parser.add_argument("--cases", type=int, default=None, help="stop after this many cases (no limit)")
    parser.add_argument("--seed", type=int, default=0, help="the first case's seed; case k is seed + k (0)")
    parser.add_argument("--device", default=None, help="cpu, cuda:0, ... (the first GPU if there is one, else cpu)")
    parser.add_argument("--depths", type=int, nargs=2, default=list(DEPTHS), metavar=("LO", "HI"),
                        help="draw octree depths from LO to HI (3 6); deeper fields take longer and more memory")
    parser.add_argument("--out", default=None, help="write the counts and problems as JSON here")


def run(args: argparse.Namespace) -> int:
    """Exit status 1 where a problem was found."""
    if args.depths[0] > args.depths[1]:  # each within 1..10 is checked with every bench's flags (_cli.py)
        raise BenchFlagError(f"--depths takes LO before HI, got {args.depths[0]} {args.depths[1]}")
    device = start_warp(args.device)
    result = check(seconds=args.seconds, cases=args.cases, seed=args.seed, device=device, depths=tuple(args.depths))
    print(f"{result['cases']} cases in {result['seconds']} s on {result['device']} ({result['compared']} compared with "
          f"the oracle, {result['refused']} refused, {result['cases_with_signs_estimated']} with sides estimated by "
          f"walks cut at their budget): {len(result['problems'])} problems")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 1 if result["problems"] else 0


def main() -> int:
    from badf.bench._cli import main_of

    return main_of("random-check")


if __name__ == "__main__":
    raise SystemExit(main())
