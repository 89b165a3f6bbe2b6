"""Error against run time: the ADF at several depths (surface-coverage refinement and the paper's centroid
rule), exact queries, the dense-grid baseline and CPU peers, all against the float64 oracle on the same
points; the switches that leave work out; and the stability table.

    badf bench accuracy [--device cuda:0] [--meshes NAME,...] [--depths 5,6,7,8,9] [--out-dir docs]

Writes <out-dir>/results/accuracy-<device>.json, <out-dir>/accuracy-<device>.md and two PNG plots beside it.
Errors are absolute and in bounding-box diagonals of the mesh; times are medians in ms after a warm-up
("wall": what a caller waits, host transfers included).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import multiprocessing
import os
import pathlib
import platform
import re
import statistics
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from badf.bench import _oracle as oracle
from badf.bench import _tolerances as tol
from badf.bench._cases import domain_of, near_surface, shared_mesh, stability_cases, surface_samples
from badf.bench._common import (bench_device_name, deform, find_mesh, mesh_folders, names_a_path, print_table,
                                start_warp, timestamp)

SHARED_MESHES = ("stanford-bunny", "armadillo-86k", "spot", "fandisk", "rocker-arm", "homer", "vlasic_samba",
                 "sumner_horse_gallop")
# Midpoint subdivision of the bunny: every triangle into 4 coplanar ones, so the surface is the bunny's own.
SUBDIVIDED = {"bunny-278k": 1, "bunny-1.1m": 2}
SUBDIVIDED_FROM = "stanford-bunny"
# what runs when no --meshes is given: those of them not in the data folders are skipped (named ones never are)
DEFAULT_MESHES = ",".join(SHARED_MESHES + tuple(SUBDIVIDED))
DEFAULT_SWITCH_MESHES = "stanford-bunny,armadillo-86k,sumner_horse_gallop"
POINT_SETS = ("uniform", "near", "surface")


@dataclass
class Mesh:
    name: str
    vertices: np.ndarray  # float32 (N, 3)
    faces: np.ndarray  # int32 (M, 3)
    truth_of: str  # the mesh whose oracle answers hold for this one (itself, or the bunny for its subdivisions)
    closed: bool = False
    diag: float = 0.0
    off_truth: float = 0.0  # largest distance of a sample of its vertices from the truth mesh, in diagonals


@dataclass
class Truth:
    """Points and the oracle's answers: unsigned distance, winding number, and their signed distance."""

    points: np.ndarray
    distance: np.ndarray
    winding: np.ndarray | None = None

    @property
    def signed(self) -> np.ndarray:
        if self.winding is None:
            return self.distance
        return np.where(np.abs(self.winding) > 0.5, -self.distance, self.distance)

    @property
    def confident(self) -> np.ndarray | None:
        """Points whose sign the oracle is sure of (winding number clear of 1/2), or None (no sign check)."""
        if self.winding is None:
            return None
        return np.abs(np.abs(self.winding) - 0.5) > tol.WINDING_CONFIDENCE


@dataclass
class PointSets:
    uniform: Truth
    surface: Truth
    near: dict[int, Truth] = field(default_factory=dict)  # by depth: within two finest cells of that depth

    def of(self, name: str, depth: int) -> Truth:
        return self.near[depth] if name == "near" else getattr(self, name)


# -- meshes ---------------------------------------------------------------------------------------------
def _findable(name: str) -> bool:
    """Whether `name` is a file that exists or a mesh in the data folders (for a subdivided bunny: the bunny;
    they were counted as there without it, so a run with no data folders measured nothing and exited 0)."""
    try:
        return find_mesh(SUBDIVIDED_FROM if name in SUBDIVIDED else name).exists()
    except FileNotFoundError:
        return False


def load_mesh(name: str) -> Mesh:
    from badf.server.adf._sign import analyse_topology

    if name in SUBDIVIDED:
        import trimesh
        from tqdm import tqdm

        vertices, faces = shared_mesh(SUBDIVIDED_FROM)
        v, f = vertices.astype(np.float64), faces
        for _ in tqdm(range(SUBDIVIDED[name]), desc=f"subdividing the bunny into {name}", file=sys.stderr):
            v, f = trimesh.remesh.subdivide(v, f)
        mesh = Mesh(name, v.astype(np.float32), np.asarray(f, np.int32), SUBDIVIDED_FROM)
        # the new vertices are rounded to float32: how far that puts them off the bunny's surface
        sample = mesh.vertices[np.random.default_rng(0).choice(len(mesh.vertices), 500, replace=False)]
        mesh.off_truth = float(oracle.nearest(sample, vertices, faces).distance.max() / oracle.bbox_diagonal(vertices))
    else:
        vertices, faces = shared_mesh(name)
        mesh = Mesh(name, vertices, faces, name)
    mesh.closed = analyse_topology(mesh.faces, mesh.vertices).closed
    mesh.diag = oracle.bbox_diagonal(mesh.vertices)
    return mesh


# -- the oracle, over processes -------------------------------------------------------------------------
def _oracle_chunk(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, with_winding: bool):
    distance = oracle.nearest(points, vertices, faces).distance
    winding = oracle.winding_number(points, vertices, faces) if with_winding else None
    return distance, winding


class OraclePool:
    """The float64 oracle spread over worker processes by chunks of points (spawned, not forked)."""

    def __init__(self, workers: int):
        self.workers = workers
        context = multiprocessing.get_context("spawn")
        self.pool = concurrent.futures.ProcessPoolExecutor(max_workers=workers, mp_context=context)

    def truth(self, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *, with_winding: bool) -> Truth:
        chunks = np.array_split(points, max(1, min(len(points) // 50, 4 * self.workers)))
        futures = [self.pool.submit(_oracle_chunk, c, vertices, faces, with_winding) for c in chunks]
        parts = [f.result() for f in futures]
        distance = np.concatenate([p[0] for p in parts])
        winding = np.concatenate([p[1] for p in parts]) if with_winding else None
        return Truth(points, distance, winding)

    def close(self) -> None:
        self.pool.shutdown()


def make_point_sets(mesh: Mesh, domain: tuple[np.ndarray, float], depths: list[int], args, pool: OraclePool) -> PointSets:
    """Uniform points in the domain, surface samples, and per depth points within two finest cells of the
    surface; with the oracle's answers (the surface samples are on the surface: no sign there)."""
    centre, side = domain
    rng = np.random.default_rng(20261121)
    v = mesh.vertices.astype(np.float64)
    uniform = centre + (rng.random((args.points, 3)) - 0.5) * side
    surface = surface_samples(v, mesh.faces, args.points, rng)
    sets = PointSets(pool.truth(uniform, v, mesh.faces, with_winding=True),
                     pool.truth(surface, v, mesh.faces, with_winding=False))
    for depth in depths:
        on = surface_samples(v, mesh.faces, args.near_points, rng)
        near = near_surface(on, 2.0 * side / (1 << depth), rng)
        sets.near[depth] = pool.truth(near, v, mesh.faces, with_winding=True)
    return sets


# -- measuring ------------------------------------------------------------------------------------------
# An object's first frames are not its steady ones: the first is planned from an estimate of its sizes, the second
# from what the first found, the third is captured as a CUDA graph that the fourth replays (docs/engine.md, "Planned
# frames and CUDA graphs"). Timing from the second frame put two of five timed frames among those.
UPDATE_WARM_UP = 3


def timed_ms(fn, device: str, *, repeat: int, budget_s: float, warm_up: int = 1) -> float:
    """Median wall time (ms) of fn() over up to `repeat` runs after `warm_up` untimed ones, stopping once `budget_s`
    is spent."""
    import warp as wp

    for _ in range(warm_up):
        fn()
    wp.synchronize_device(device)
    times: list[float] = []
    while len(times) < repeat and sum(times) < budget_s * 1e3:
        start = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - start) * 1e3)
    return float(statistics.median(times))


def error_stats(answer: np.ndarray, truth: Truth, diag: float, *, against: np.ndarray | None = None) -> dict:
    """Max, p99 and mean absolute error in diagonals, and the rate of wrong signs where the oracle is sure."""
    reference = truth.signed if against is None else against
    error = np.abs(answer.astype(np.float64) - reference) / diag
    stats = {"max": float(error.max()), "p99": float(np.percentile(error, 99)), "mean": float(error.mean()),
             "nonfinite": int(np.count_nonzero(~np.isfinite(answer)))}
    confident = truth.confident
    if confident is not None and confident.any():
        wrong = (answer < 0)[confident] != (reference < 0)[confident]
        stats["wrong_sign_rate"] = float(np.mean(wrong))
    else:
        stats["wrong_sign_rate"] = None
    return stats


def answers_of(answer_fn, sets: PointSets, depth: int) -> dict[str, np.ndarray]:
    return {name: np.asarray(answer_fn(sets.of(name, depth).points)) for name in POINT_SETS}


def errors_of(answers: dict[str, np.ndarray], sets: PointSets, depth: int, diag: float) -> dict:
    return {name: error_stats(answers[name], sets.of(name, depth), diag) for name in POINT_SETS}


def measure_adf(mesh: Mesh, sets: PointSets, depth: int, options: dict, args, *, mode: str = "adf",
                outputs: tuple[str, ...] = ("distance",)) -> tuple[dict, object, dict[str, np.ndarray]]:
    """One ADF configuration: build, accuracy (on the mesh as given), query and coherent-update times, memory.

    Returns the row, the field (left at its last timed frame) and its distances at the point sets on the
    mesh as given.
    """
    from badf.server.adf import DistanceField

    device = args.device
    holder = {}

    def build():
        holder["field"] = DistanceField(mesh.vertices, mesh.faces, depth=depth, device=device, **options)

    build_ms = timed_ms(build, device, repeat=args.repeat, budget_s=args.budget)
    distance_field = holder["field"]
    nbytes = distance_field.stats()["device_bytes"]
    answers = answers_of(lambda p: distance_field.query(p, mode=mode).distance, sets, depth)
    errors = errors_of(answers, sets, depth, mesh.diag)
    batch = query_batch(distance_field, args.query_batch)
    query_ms = timed_ms(lambda: distance_field.query(batch, mode=mode, outputs=outputs), device, repeat=args.repeat,
                        budget_s=args.budget)
    frames = iter([deform(mesh.vertices, 0.02 * k) for k in range(1, args.repeat + UPDATE_WARM_UP + 1)])
    update_ms = timed_ms(lambda: distance_field.update(next(frames)), device, repeat=args.repeat, budget_s=args.budget,
                         warm_up=UPDATE_WARM_UP)
    row = {
        "mesh": mesh.name, "mode": mode, "depth": depth, "options": options, "outputs": list(outputs),
        "build_ms": build_ms, "update_ms": update_ms, "query_ms_per_million": query_ms * 1e6 / len(batch),
        "device_bytes": nbytes, "unique_corners": distance_field.stats()["counts"]["unique_corners"],
        "sign": distance_field.info()["sign"], "errors": errors,
    }
    return row, distance_field, answers


def query_batch(distance_field, count: int) -> np.ndarray:
    centre, side, _ = domain_of(distance_field)
    rng = np.random.default_rng(7)
    return ((rng.random((count, 3)) - 0.5) * side + centre).astype(np.float32)


def measure_dense(mesh: Mesh, sets: PointSets, depth: int, domain: tuple[np.ndarray, float], args) -> dict:
    from badf.bench._dense import DenseGrid

    centre, side = domain
    device = args.device

    def local(points):
        return (np.asarray(points, np.float64) - centre).astype(np.float32)

    grid = DenseGrid(local(mesh.vertices), mesh.faces, side=side, depth=depth, device=device)
    build_ms = timed_ms(grid.build, device, repeat=args.repeat, budget_s=args.budget)
    errors = errors_of(answers_of(lambda p: grid.query(local(p)), sets, depth), sets, depth, mesh.diag)
    batch = local((np.random.default_rng(7).random((args.query_batch, 3)) - 0.5) * side + centre)
    query_ms = timed_ms(lambda: grid.query(batch), device, repeat=args.repeat, budget_s=args.budget)
    frames = iter([local(deform(mesh.vertices, 0.02 * k)) for k in range(1, args.repeat + 2)])
    update_ms = timed_ms(lambda: grid.update(next(frames)), device, repeat=args.repeat, budget_s=args.budget)
    return {
        "mesh": mesh.name, "mode": "dense", "depth": depth, "options": {"lattice": f"{grid.count}^3"},
        "outputs": ["distance"], "build_ms": build_ms, "update_ms": update_ms,
        "query_ms_per_million": query_ms * 1e6 / len(batch), "device_bytes": grid.nbytes(),
        "sign": "pseudonormal (warp)", "errors": errors,
    }


def measure_switches(mesh: Mesh, sets: PointSets, depth: int, args) -> list[dict]:
    """Each switch that leaves work out (or, for the BVH's shape, moves it to registration), against the default
    configuration at the same depth."""
    rows = []
    reference, ref_field, ref_answers = measure_adf(mesh, sets, depth, {}, args)
    reference["switch"] = "default: auto sign, no band, coherence on, halo 1, distance only"
    rows.append(reference)
    cell = ref_field.info()["domain"]["finest_cell"]

    row, _, answers = measure_adf(mesh, sets, depth, {"sign": "none"}, args)
    row["switch"] = "sign off (unsigned)"
    row["changes"] = "errors against the unsigned truth: " + _brief({
        name: error_stats(answers[name], sets.of(name, depth), mesh.diag, against=sets.of(name, depth).distance)
        for name in POINT_SETS})
    rows.append(row)

    if reference["sign"] == "pseudonormal":  # auto found the mesh closed, facing out, its parts apart
        row, _, answers = measure_adf(mesh, sets, depth, {"sign": "pseudonormal"}, args)
        row["switch"] = ("pseudonormals asked for (no look for parts running into each other, at registration or "
                         "by frame)")
        row["difference_to_auto"] = _largest_difference(answers, ref_answers)
        row["changes"] = f"max difference to auto's answers: {row['difference_to_auto'] / mesh.diag:.1e} diag"
        rows.append(row)

    band = 4.0 * cell
    row, _, answers = measure_adf(mesh, sets, depth, {"band": band}, args)
    row["switch"] = f"narrow band of 4 finest cells ({band / mesh.diag:.3g} diag)"
    clamped = {name: error_stats(answers[name], sets.of(name, depth), mesh.diag,
                                 against=np.clip(sets.of(name, depth).signed, -band, band)) for name in POINT_SETS}
    fraction = float(np.mean(np.abs(sets.uniform.signed) >= band))
    row["changes"] = (f"{100 * fraction:.0f}% of uniform points clamped to +-band; errors against the clamped truth: "
                      + _brief(clamped))
    rows.append(row)

    row, field_off, _ = measure_adf(mesh, sets, depth, {"coherence": False}, args)
    row["switch"] = "coherence off (for a rigid object, which is only built)"
    frame = deform(mesh.vertices, 0.37)
    ref_field.update(frame)
    field_off.update(frame)
    points = sets.near[depth].points
    difference = float(np.abs(field_off.query(points).distance - ref_field.query(points).distance).max())
    row["changes"] = f"after one more identical frame, max difference to coherence on: {difference / mesh.diag:.1e} diag"
    rows.append(row)

    row, _, _ = measure_adf(mesh, sets, depth, {"halo": 0}, args)
    row["switch"] = "halo 0 (no ring of finest cells around the surface)"
    rows.append(row)

    # the BVH's other shape than the one auto takes on this device (sah on the CPU, morton on CUDA)
    other = "morton" if ref_field.info()["bvh"] == "sah" else "sah"
    described = {"sah": "BVH shaped by surface area (made on the host at registration, then kept)",
                 "morton": "BVH linked over Morton codes on the device (the paper's)"}[other]
    for mode in ("adf", "exact"):
        row, _, answers = measure_adf(mesh, sets, depth, {"bvh": other}, args, mode=mode)
        row["switch"] = f"{described}, {mode} query"
        if mode == "adf":
            row["difference_to_default"] = _largest_difference(answers, ref_answers)
            row["changes"] = f"max difference to the default's answers: {row['difference_to_default'] / mesh.diag:.1e} diag"
        rows.append(row)

    for mode in ("adf", "exact"):
        row, _, _ = measure_adf(mesh, sets, depth, {}, args, mode=mode, outputs=("distance", "closest_point", "normal",
                                                                                 "face"))
        row["switch"] = f"{mode} query with all four outputs (compare with distance only)"
        rows.append(row)
    return rows


def _largest_difference(answers: dict, reference: dict) -> float:
    """The largest difference between two configurations' answers over every point set."""
    return max(float(np.abs(answers[name] - reference[name]).max()) for name in POINT_SETS)


def _brief(errors: dict) -> str:
    return ", ".join(f"{name} max {e['max']:.1e}" for name, e in errors.items())


def measure_peers(mesh: Mesh, sets: PointSets, depth: int, domain: tuple[np.ndarray, float], args
                  ) -> tuple[list[dict], dict]:
    """CPU peers on the same points; query time from one call on a batch of the same size as the engine's."""
    from badf.bench._peers import available_peers

    centre, side = domain
    batch = (np.random.default_rng(7).random((args.query_batch, 3)) - 0.5) * side + centre
    peers, skipped = available_peers(mesh.vertices, mesh.faces, mesh.closed)
    rows = []
    for peer in peers:
        errors = errors_of(answers_of(peer.query, sets, depth), sets, depth, mesh.diag)
        start = time.perf_counter()
        peer.query(batch)
        query_ms = (time.perf_counter() - start) * 1e3
        rows.append({"mesh": mesh.name, "mode": "peer", "peer": peer.name, "depth": None, "sign": peer.sign,
                     "build_ms": peer.build_ms, "update_ms": None, "query_ms_per_million": query_ms * 1e6 / len(batch),
                     "device_bytes": None, "errors": errors})
    return rows, skipped


def run_stability(args) -> list[dict]:
    from badf.bench._cases import KNOWN_ENGINE_BUGS

    rows = []
    for case in stability_cases(large_batch=args.large_batch):
        start = time.perf_counter()
        try:
            outcome = case.run(args.device)
            passed, measured = outcome.passed, outcome.measured
            numbers = outcome.numbers
        except FileNotFoundError as missing:
            passed, measured, numbers = None, f"skipped: {missing}", {}
        rows.append({"group": case.group, "case": case.name, "expected": case.expected, "passed": passed,
                     "measured": measured, "known_engine_bug": KNOWN_ENGINE_BUGS.get(case.name),
                     "seconds": round(time.perf_counter() - start, 2), "numbers": numbers})
        print(f"  {'pass' if passed else 'FAIL' if passed is False else 'skip'}  {case.name}: {measured}", flush=True)
    return rows


# -- driver ---------------------------------------------------------------------------------------------
def device_slug(device: str) -> str:
    import warp as wp

    d = wp.get_device(device)
    name = d.name if d.is_cuda else "cpu"
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def run(args: argparse.Namespace) -> int:
    if args.render:
        try:
            report = json.loads(pathlib.Path(args.render).read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            print(f"badf bench accuracy: --render {args.render}: not a results JSON file ({error})", file=sys.stderr)
            return 2
        if not isinstance(report, dict) or report.get("benchmark") != "accuracy" or "rows" not in report:
            kind = report.get("benchmark") if isinstance(report, dict) else None
            print(f"badf bench accuracy: --render {args.render}: not the results of `badf bench accuracy`"
                  + (f" (they are of `badf bench {kind}`)" if isinstance(kind, str) else ""), file=sys.stderr)
            return 2
        write_outputs(report, pathlib.Path(args.out_dir), pathlib.Path(args.render).stem.removeprefix("accuracy-"))
        return 0
    from badf.server.adf import DistanceField

    args.device = start_warp(args.device)
    depths = sorted(int(d) for d in args.depths.split(","))
    names = [n for n in args.meshes.split(",") if n]
    if not names:
        print("badf bench accuracy: --meshes names no mesh", file=sys.stderr)
        return 2
    available = [name for name in names if _findable(name)]
    explicit = args.meshes != DEFAULT_MESHES  # names the user gave are all measured; the default's missing are skipped
    for name in [n for n in names if n not in available]:
        if name not in SUBDIVIDED and names_a_path(name):
            print(f"badf bench accuracy: {name}: no such file", file=sys.stderr)  # a path, not a name to skip
            return 2
        if explicit:
            print(f"badf bench accuracy: --meshes {name}: not a mesh file here, nor a mesh in "
                  f"{', '.join(map(str, mesh_folders()))} (set BADF_SHARED_DATA to a folder that holds it)",
                  file=sys.stderr)
            return 2
    switches = [n for n in args.switch_meshes.split(",") if n and n != "none"]
    strays = [n for n in switches if n not in names]
    if args.switch_meshes != DEFAULT_SWITCH_MESHES and strays:
        print(f"badf bench accuracy: --switch-meshes {', '.join(strays)}: not among --meshes", file=sys.stderr)
        return 2
    if not available:  # before the stability table, which takes minutes
        print(f"badf bench accuracy: none of --meshes {args.meshes} is a mesh file or a mesh in "
              f"{', '.join(map(str, mesh_folders()))}; set BADF_SHARED_DATA to a folder that holds "
              "them", file=sys.stderr)
        return 2
    started = time.perf_counter()
    report = {
        "benchmark": "accuracy", "date": timestamp(), "device": bench_device_name(args.device),
        "host": platform.node(), "command": "badf bench accuracy " + " ".join(sys.argv[3:] if sys.argv[1:2] == ["bench"]
                                                                             else sys.argv[1:]),
        "settings": {"depths": depths, "points": args.points, "near_points": args.near_points,
                     "query_batch": args.query_batch, "repeat": args.repeat, "update_warm_up": UPDATE_WARM_UP,
                     "dense_max_depth": args.dense_max_depth,
                     "switch_depth": args.switch_depth, "oracle_workers": args.workers},
        "meshes": [], "rows": [], "switches": [], "peers": [], "peers_skipped": {}, "stability": [],
        "load_average_at_start": os.getloadavg()[0],  # other work on the machine disturbs the times
    }
    slug = device_slug(args.device)
    partial = pathlib.Path(args.out_dir) / "results" / f"accuracy-{slug}.json"
    partial.parent.mkdir(parents=True, exist_ok=True)
    if args.stability:  # first: it is short, and matters most if a long run is cut off
        print("stability cases:", flush=True)
        report["stability"] = run_stability(args)
        partial.write_text(json.dumps(report, indent=1))
    pool = OraclePool(args.workers)
    truths: dict[str, PointSets] = {}
    try:
        for name in names:
            try:
                mesh = load_mesh(name)
            except FileNotFoundError as missing:
                print(f"skipping {name}: {missing}")
                continue
            probe = DistanceField(mesh.vertices, mesh.faces, depth=depths[0], device=args.device)
            centre, side, _ = domain_of(probe)
            if mesh.truth_of not in truths:
                t0 = time.perf_counter()
                truth_mesh = mesh if mesh.truth_of == mesh.name else load_mesh(mesh.truth_of)
                set_depths = sorted(set(depths) | {args.switch_depth})
                truths[mesh.truth_of] = make_point_sets(truth_mesh, (centre, side), set_depths, args, pool)
                print(f"{name}: oracle for {args.points} uniform, {args.points} surface and {len(set_depths)} x "
                      f"{args.near_points} near points in {time.perf_counter() - t0:.1f} s", flush=True)
            sets = truths[mesh.truth_of]
            report["meshes"].append({"name": name, "vertices": len(mesh.vertices), "faces": len(mesh.faces),
                                     "closed": mesh.closed, "diag": mesh.diag, "domain_side": side, "truth_of": mesh.truth_of,
                                     "vertices_off_truth_diag": mesh.off_truth,
                                     "sign": probe.info()["sign"]})
            del probe
            for depth in depths:
                for refine, options in (("surface", {}), ("centroid", {"refine": "centroid", "halo": 0})):
                    row, _, _ = measure_adf(mesh, sets, depth, options, args)
                    row["mode"] = f"adf-{refine}"
                    report["rows"].append(row)
                    _print_row(row)
                if depth <= args.dense_max_depth:
                    row = measure_dense(mesh, sets, depth, (centre, side), args)
                    report["rows"].append(row)
                    _print_row(row)
            row, _, _ = measure_adf(mesh, sets, args.switch_depth, {}, args, mode="exact")
            report["rows"].append(row)
            _print_row(row)
            if name in args.switch_meshes.split(","):
                report["switches"] += measure_switches(mesh, sets, args.switch_depth, args)
            if args.peers:
                rows, skipped = measure_peers(mesh, sets, args.switch_depth, (centre, side), args)
                report["peers"] += rows
                report["peers_skipped"].update(skipped)
                for row in rows:
                    _print_row(row)
            report["seconds"] = round(time.perf_counter() - started, 1)
            partial.write_text(json.dumps(report, indent=1))  # so far, in case the run is cut short
    finally:
        pool.close()
    report["load_average_at_end"] = os.getloadavg()[0]
    report["seconds"] = round(time.perf_counter() - started, 1)
    write_outputs(report, pathlib.Path(args.out_dir), slug)
    return 0


def _print_row(row: dict) -> None:
    e = row["errors"]
    label = row.get("peer") or row["mode"]
    print(f"  {row['mesh']:20s} {label:24s} depth {row['depth']!s:4s} build {_ms(row['build_ms'])} update "
          f"{_ms(row['update_ms'])} query/M {_ms(row['query_ms_per_million'])}  near max {e['near']['max']:.2e} "
          f"p99 {e['near']['p99']:.2e}  uniform max {e['uniform']['max']:.2e}", flush=True)


def _ms(value) -> str:
    return "   -    " if value is None else f"{value:8.2f}"


def write_outputs(report: dict, out_dir: pathlib.Path, slug: str) -> None:
    from badf.bench._accuracy_report import render_markdown, render_plots

    (out_dir / "results").mkdir(parents=True, exist_ok=True)
    json_path = out_dir / "results" / f"accuracy-{slug}.json"
    json_path.write_text(json.dumps(report, indent=1))
    plots = render_plots(report, out_dir, slug)
    md_path = out_dir / f"accuracy-{slug}.md"
    md_path.write_text(render_markdown(report, [p.name for p in plots], json_path.relative_to(out_dir)))
    print("wrote", json_path, md_path, *plots)
    stability = report["stability"]
    if stability:
        print_table("stability", ["case", "result"], [[r["case"], "pass" if r["passed"] else
                                                       ("skip" if r["passed"] is None else "FAIL")] for r in stability])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default=None, help="cpu, cuda:0, ... (default: the first GPU, else cpu)")
    parser.add_argument("--meshes", default=DEFAULT_MESHES,
                        help="comma-separated mesh names (shared data set, or bunny-278k / bunny-1.1m) or mesh files "
                             "(.npz with vertices and faces, or any file trimesh reads)")
    parser.add_argument("--depths", default="5,6,7,8,9", help="ADF depths, comma-separated")
    parser.add_argument("--dense-max-depth", type=int, default=9, help="dense-grid baseline up to this depth")
    parser.add_argument("--points", type=int, default=1000, help="uniform points, and surface samples, per mesh")
    parser.add_argument("--near-points", type=int, default=500, help="points within two finest cells, per depth")
    parser.add_argument("--query-batch", type=int, default=1_000_000, help="points per timed query call")
    parser.add_argument("--repeat", type=int, default=5, help="timed repeats per measurement (at most)")
    parser.add_argument("--budget", type=float, default=1.0, help="seconds after which a measurement stops repeating")
    parser.add_argument("--switch-depth", type=int, default=7, help="depth of the exact-query and switch rows")
    parser.add_argument("--switch-meshes", default=DEFAULT_SWITCH_MESHES,
                        help="meshes that get the switch rows")
    parser.add_argument("--peers", action="store_true", help="also measure CPU peers (Open3D, libigl) where installed")
    parser.add_argument("--no-stability", dest="stability", action="store_false", help="skip the stability table")
    parser.add_argument("--large-batch", type=int, default=10_000_000, help="points of the large-batch stability case")
    parser.add_argument("--workers", type=int, default=len(os.sched_getaffinity(0)), help="oracle processes")
    parser.add_argument("--out-dir", default="docs", help="where the markdown, plots and results/ JSON go")
    parser.add_argument("--render", default=None, metavar="JSON",
                        help="only write the markdown and plots of an earlier run's results/accuracy-*.json")


def main() -> int:
    from badf.bench._cli import main_of

    return main_of("accuracy")


if __name__ == "__main__":
    raise SystemExit(main())
