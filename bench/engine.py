"""Engine benchmark: per-stage build and update times, memory, and the dense-grid baseline a Warp user
would write instead (wp.Mesh + mesh_query_point_sign_normal over every grid point).

    python -m badf.bench.engine --mesh PATH.npz [--device cuda:0] [--depth 7] [--out results.json]

Times are medians over repeats after a warm-up: "gpu" is the device time between the first and the last
stage's events (CUDA) or the wall time of the synchronous CPU launches; "wall" is what a caller waits,
from the call to the end of the device work, Python and read-backs included.
"""


import argparse
import itertools
import json
import platform
import statistics
import time

import numpy as np

from badf.bench._common import BenchFlagError, bench_device_name, deform, print_table, start_warp, timestamp
from badf.bench._oracle import ORACLE_SAMPLE, errors_against, signed_distance
from badf.protocol import BVH_SHAPES
from badf.server._mesh_files import MESH_HELP, read_mesh


def _median(values):
    return float(statistics.median(values))


def _time_wall(fn, device, repeat: int) -> list[float]:
    import warp as wp

    out = []
    for i in range(repeat):
        wp.synchronize_device(device)
        start = time.perf_counter()
        fn(i)
        wp.synchronize_device(device)
        out.append((time.perf_counter() - start) * 1e3)
    return out


def _time_updates(field, frames, device: str) -> tuple[list[float], list[dict]]:
    """Each frame's update: wall ms, and the field's per-stage times."""
    walls, stages = [], []
    for frame in frames:
        walls += _time_wall(lambda _: field.update(frame), device, 1)
        stages.append(field.stats()["times_ms"])
    return walls, stages


def measure_field(vertices, faces, *, device: str, repeat: int, **options) -> dict:
    """Build and coherent-update times (median), per-stage medians, counts and memory of one configuration."""
    # graphs=False: planned frames run their kernels one by one instead of replaying a captured CUDA graph;
    # one_stream=True: no work beside the frame's stream (BVH refit beside the octree, winding numbers beside
    # the searches): all of it queued in order
    from badf.server.adf._buffers import SideStream

    field_options = {k: v for k, v in options.items() if k not in ("graphs", "one_stream")}
    graphs = options.get("graphs", True)
    SideStream.allowed = not options.get("one_stream", False)
    try:
        return _measure_field(vertices, faces, device=device, repeat=repeat, options=options, graphs=graphs,
                              field_options=field_options)
    finally:
        SideStream.allowed = True


def _measure_field(vertices, faces, *, device: str, repeat: int, options: dict, graphs: bool,
                   field_options: dict) -> dict:
    from badf.server.adf import DistanceField

    field = DistanceField(vertices, faces, device=device, **field_options)  # warm-up: compiles kernels
    field.update(deform(vertices, 0.5))
    builds, build_stages, builds_measured = [], [], 0

    def build(_):
        nonlocal field
        field = DistanceField(vertices, faces, device=device, **field_options)
        field.use_graphs = graphs

    for i in range(repeat):
        builds += _time_wall(build, device, 1)
        build_stages.append(field.stats()["times_ms"])
        builds_measured += field.stats()["measured_frames"] > 0  # its first frame's plan missed, or none was made
    # a new frame every time: the wobble advances 0.02 of its period per frame
    frames = [deform(vertices, 0.02 * k) for k in range(repeat + 1)]
    updates, update_stages = _time_updates(field, frames[1:], device)
    stats = field.stats()
    # frames thrown half the mesh's extent further along x each time: every one moves the domain (and
    # rebuilds the BVH); on another object, so the queries below see the coherent frames' field
    mover = DistanceField(vertices, faces, device=device, **field_options)
    mover.use_graphs = graphs
    step = np.array([0.5 * float(np.max(vertices.max(axis=0) - vertices.min(axis=0))), 0.0, 0.0], vertices.dtype)
    moving, moving_stages = _time_updates(mover, [frames[i] + i * step for i in range(1, repeat + 1)], device)
    mover_stats = mover.stats()

    def stage_medians(stage_list):
        names = stage_list[0].keys()
        return {name: round(_median([s.get(name, 0.0) for s in stage_list]), 4) for name in names}

    return {
        "options": options,
        "build_wall_ms": round(_median(builds), 4),
        "build_gpu_ms": round(_median([s["total"] for s in build_stages]), 4),
        "update_wall_ms": round(_median(updates), 4),
        "update_gpu_ms": round(_median([s["total"] for s in update_stages]), 4),
        "build_stages_ms": stage_medians(build_stages),
        "builds_measured": builds_measured,
        "update_stages_ms": stage_medians(update_stages),
        "moving_update_wall_ms": round(_median(moving), 4),
        "moving_update_gpu_ms": round(_median([s["total"] for s in moving_stages]), 4),
        "moving_update_stages_ms": stage_medians(moving_stages),
        "bvh_shape_ms": field.stats()["bvh_shape_ms"],
        "moving_domain_moves": mover_stats["domain_moves"],
        "moving_measured_frames": mover_stats["measured_frames"],
        "counts": stats["counts"],
        "replans": stats["replans"],
        "graph_captures": stats["graph_captures"],
        "device_bytes": stats["device_bytes"],
        "memory_bytes": stats["memory_bytes"],
        "field": field,
        "vertices": frames[repeat],
    }


def quarter_of_the_box(vertices: np.ndarray) -> list[list[float]]:
    """A region of interest: the mesh's bounding box (grown by 5%) cut to its lower half in x and in y."""
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    margin = 0.05 * (hi - lo)
    upper = hi + margin
    upper[:2] = (lo[:2] + hi[:2]) / 2
    return [(lo - margin).tolist(), upper.tolist()]


def measure_queries(field, vertices, faces, *, device: str, repeat: int, count: int = 65536) -> dict:
    """Timed ADF and exact queries of `count` points spread over the mesh's box, with each mode's error
    against the float64 oracle (winding-number sign) on a sample of them, and ADF's against exact on all."""
    rng = np.random.default_rng(0)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    points = rng.uniform(lo, hi, size=(count, 3)).astype(np.float32)
    out = {}
    results = {}
    for mode in ("adf", "exact"):
        field.query(points, mode=mode)
        times = _time_wall(lambda _: results.__setitem__(mode, field.query(points, mode=mode)), device, repeat)
        out[f"query_{mode}_ms"] = round(_median(times), 4)
    error = np.abs(results["adf"].distance - results["exact"].distance)
    diag = float(np.linalg.norm((hi - lo).astype(np.float64)))  # float32's square of a 1e-39 extent is 0
    out["query_points"] = count
    out["adf_vs_exact_max_error_diag"] = float(error.max() / diag)
    out["adf_vs_exact_mean_error_diag"] = float(error.mean() / diag)
    truth = signed_distance(points[:ORACLE_SAMPLE], vertices, faces)
    for mode in ("adf", "exact"):
        out[f"{mode}_vs_oracle"] = errors_against(results[mode].distance[:ORACLE_SAMPLE], truth, vertices)
    return out


def _rigid_motion(vertices: np.ndarray, k: int):
    """Frame k of a rigid motion, as a function of (P, 3) points: turned 0.05 k radians about (1, 1, 1) about the
    mesh's box's centre and carried 0.1 k of the box's extent along x, in float64."""
    v = vertices.astype(np.float64)
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    angle, axis = 0.05 * k, np.ones(3) / np.sqrt(3.0)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * (cross @ cross)
    shift = centre + [0.1 * k * float(np.max(v.max(axis=0) - v.min(axis=0))), 0.0, 0.0]
    return lambda points: (np.asarray(points, np.float64) - centre) @ rotation.T + shift


def measure_rigid(vertices, faces, *, device: str, depth: int, repeat: int, count: int = 65536) -> dict:
    """Frames that only turn and shift the mesh, taken as rigid (rigid="auto": the field kept, the queries moved
    into it) and rebuilt (rigid="off"): each frame's wall time, then queries of `count` points over the last
    frame's box, and their error against the float64 oracle on the moved mesh; and the host's test of a deforming
    frame, which every frame of a deforming object pays under rigid="auto"."""
    from badf.server.adf import DistanceField
    from badf.server.adf._rigid import RigidTest

    frames = [_rigid_motion(vertices, k)(vertices) for k in range(1, repeat + 1)]
    last = frames[-1]
    # points spread over the mesh's own box, carried with it: the same points about the body for both fields
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    carried = _rigid_motion(vertices, repeat)(np.random.default_rng(0).uniform(lo, hi, size=(count, 3)))
    points = carried.astype(np.float32)
    truth = signed_distance(points[:ORACLE_SAMPLE], last, faces)
    rows = {}
    for mode in ("auto", "off"):
        field = DistanceField(vertices, faces, depth=depth, device=device, rigid=mode)
        field.update(_rigid_motion(vertices, repeat + 5)(vertices))  # warm-up: compiles, and a frame of its own
        field.update(vertices)
        before = field.stats()["rigid_frames"]
        updates = [_time_wall(lambda _: field.update(frame), device, 1)[0] for frame in frames]
        row = {"update_wall_ms": round(_median(updates), 4), "rigid_frames": field.stats()["rigid_frames"] - before}
        for query_mode in ("adf", "exact"):
            answers = {}
            field.query(points, mode=query_mode)
            times = _time_wall(lambda _: answers.__setitem__("r", field.query(points, mode=query_mode)), device, repeat)
            row[f"query_{query_mode}_ms"] = round(_median(times), 4)
            row[f"{query_mode}_vs_oracle"] = errors_against(answers["r"].distance[:ORACLE_SAMPLE], truth, last)
        if mode == "auto":
            row.update(_rigid_run_memory(field, vertices, device))
        rows[mode] = row
        del field
    test = RigidTest(vertices, None)
    deforming = deform(vertices, 0.02)
    diagonal = float(np.linalg.norm((vertices.max(axis=0) - vertices.min(axis=0)).astype(np.float64)))
    tests = []
    for _ in range(max(repeat, 20)):
        start = time.perf_counter()
        test.pose(vertices, deforming, 1e-6 * diagonal)
        tests.append((time.perf_counter() - start) * 1e3)
    return {"depth": depth, "frames": repeat, "query_points": count, "rigid": rows["auto"], "rebuilt": rows["off"],
            "deforming_frame_test_ms": round(_median(tests), 4)}


def _rigid_run_memory(field, vertices, device: str) -> dict:
    """What a field of rigid frames holds before and after a run long enough for its frame scratch to be given back,
    and the wall time of the two deforming frames after it (the first allocates the scratch again, and on CUDA runs
    eagerly before its frame is captured again)."""
    from badf.server.adf._field import _SCRATCH_GIVEN_BACK_AFTER

    base = deform(vertices, 0.01)
    field.update(base)  # a deforming frame: rebuilt, the run of rigid frames starts after it
    before = field.stats()["device_bytes"]
    for k in range(_SCRATCH_GIVEN_BACK_AFTER):
        field.update(_rigid_motion(vertices, k + 1)(base))
    after = field.stats()["device_bytes"]
    walls = [_time_wall(lambda _: field.update(deform(vertices, 0.02 * (k + 1))), device, 1)[0] for k in range(3)]
    return {"rigid_run_frames": _SCRATCH_GIVEN_BACK_AFTER, "device_mib_before_run": round(before / 2**20, 2),
            "device_mib_after_run": round(after / 2**20, 2), "scratch_given_back": field.stats()["scratch_given_back"],
            "rebuild_after_run_wall_ms": [round(w, 4) for w in walls]}


def print_rigid(rigid: dict) -> None:
    print_table(f"rigid frames (turned and shifted, float64), depth {rigid['depth']}: medians of {rigid['frames']} "
                f"frames and of the queries of {rigid['query_points']:,} points over the mesh's box, carried with it; "
                "errors against the float64 oracle, max diagonals",
                ["rigid", "frames taken as rigid", "update wall ms", "adf query ms", "exact query ms", "adf error",
                 "exact error"],
                [[name, r["rigid_frames"], r["update_wall_ms"], r["query_adf_ms"], r["query_exact_ms"],
                  f"{r['adf_vs_oracle']['max_error_diag']:.2e}", f"{r['exact_vs_oracle']['max_error_diag']:.2e}"]
                 for name, r in (("auto", rigid["rigid"]), ("off (rebuilt)", rigid["rebuilt"]))])
    print(f"  the host's test of a deforming frame under rigid=\"auto\": {rigid['deforming_frame_test_ms']} ms")
    r = rigid["rigid"]
    print(f"  after {r['rigid_run_frames']} rigid frames in a row the frame scratch is given back: "
          f"{r['device_mib_before_run']} -> {r['device_mib_after_run']} MiB; the deforming frames after it took "
          f"{', '.join(str(w) for w in r['rebuild_after_run_wall_ms'])} ms (wall)")


def measure_violent(vertices, faces, *, device: str, depth: int, repeat: int, noise: float = 0.2) -> dict:
    """Calm deforming frames, one violent frame (every vertex thrown up to `noise` of the box's extent, kept in the
    box so that the domain stays: a simulation that blew up for a frame), then calm frames again: each phase's
    update times and memory, while the violent frame's plan is kept (its first frames after) and once it is given
    back (after _PLAN_GIVEN_BACK_AFTER calm frames in a row that need far less); the last frame's exact errors."""
    from badf.server.adf import DistanceField
    from badf.server.adf._field import _PLAN_GIVEN_BACK_AFTER

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    throw = np.random.default_rng(0).uniform(-1.0, 1.0, size=vertices.shape) * noise * float(np.max(hi - lo))
    violent = np.clip(vertices + throw, lo, hi).astype(vertices.dtype)
    calm = (deform(vertices, 0.02 * k) for k in itertools.count())
    field = DistanceField(vertices, faces, depth=depth, device=device, rigid="off")
    last = [vertices]

    def phase(frames: list[np.ndarray]) -> dict:
        walls, stages = _time_updates(field, frames, device)
        last[0] = frames[-1]
        stats = field.stats()
        return {"update_wall_ms": round(_median(walls), 4), "update_gpu_ms": round(_median([s["total"] for s in stages]), 4),
                "device_mib": round(stats["device_bytes"] / 2**20, 2), "corners": stats["counts"]["unique_corners"],
                "winding_walks_cut": stats["winding_walks_cut"]}

    def calm_frames(count: int) -> list[np.ndarray]:
        return [next(calm) for _ in range(count)]

    phase(calm_frames(3))  # warm-up: compiles kernels, captures the frame's graph
    phases = {"calm before": phase(calm_frames(repeat)), "the violent frame": phase([violent])}
    kept = min(repeat, _PLAN_GIVEN_BACK_AFTER - 2)
    phases["calm, its plan kept"] = phase(calm_frames(kept))  # the violent frame's plan in force
    phase(calm_frames(_PLAN_GIVEN_BACK_AFTER + 2 - kept))  # the give-back, a frame sized anew, the graph captured again
    phases["calm, plan given back"] = phase(calm_frames(repeat))
    stats = field.stats()
    positions, values, _ = field.corner_samples()
    pick = np.random.default_rng(1).choice(len(positions), min(len(positions), ORACLE_SAMPLE), replace=False)
    corners = errors_against(values[pick], signed_distance(positions[pick], last[0], faces), last[0])
    return {"depth": depth, "frames": repeat, "noise": noise, "phases": phases, "corners_vs_oracle": corners,
            "plans_given_back": stats["plans_given_back"], "replans": stats["replans"],
            "domain_moves": stats["domain_moves"]}


def print_violent(violent: dict) -> None:
    print_table(f"a violent frame (vertices thrown up to {violent['noise']:g} of the extent, in the box), depth "
                f"{violent['depth']}: medians of {violent['frames']} calm frames a phase; plans given back "
                f"{violent['plans_given_back']}, replans {violent['replans']}",
                ["phase", "update device ms", "update wall ms", "corners", "winding walks cut", "MiB"],
                [[name, r["update_gpu_ms"], r["update_wall_ms"], r["corners"], r["winding_walks_cut"], r["device_mib"]]
                 for name, r in violent["phases"].items()])
    print(f"  the last frame's corners against the float64 oracle (max / mean, diagonals): "
          f"{violent['corners_vs_oracle']['max_error_diag']:.2e} / {violent['corners_vs_oracle']['mean_error_diag']:.2e}")


def measure_trim(vertices, faces, *, device: str, depth: int, repeat: int, count: int = 65536,
                 large: int = 1 << 20) -> dict:
    """What `trim` gives back and what it costs after: the bytes held after deforming frames, after one query of
    `large` points with every output, and after the trim; the wall time of queries of `count` points before the trim
    and of the first after it (which allocates its buffers again), and whether its answers were the same; the update
    times of the first frame after the trim (scratch allocated again, searched from spatial seeds, on CUDA run eagerly)
    and of the frames after it."""
    from badf.server.adf import DistanceField

    frames = (deform(vertices, 0.02 * k) for k in itertools.count())
    field = DistanceField(vertices, faces, depth=depth, device=device, rigid="off")
    _time_updates(field, [next(frames) for _ in range(3)], device)  # warm-up: compiles, captures the frame's graph
    held = field.stats()["device_bytes"]
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    rng = np.random.default_rng(0)
    field.query(rng.uniform(lo, hi, size=(large, 3)).astype(np.float32), outputs=("distance", "closest_point", "normal",
                                                                                   "face"))
    after_large = field.stats()["device_bytes"]
    points = rng.uniform(lo, hi, size=(count, 3)).astype(np.float32)
    answers = {}
    before = _time_wall(lambda _: answers.__setitem__("before", field.query(points).distance), device, repeat)
    freed = field.trim()
    trimmed = field.stats()["device_bytes"]
    first_query = _time_wall(lambda _: answers.__setitem__("after", field.query(points).distance), device, 1)[0]
    first_walls, first_stages = _time_updates(field, [next(frames)], device)
    walls, stages = _time_updates(field, [next(frames) for _ in range(repeat)], device)
    return {"depth": depth, "large_query_points": large, "query_points": count,
            "device_mib_after_frames": round(held / 2**20, 2), "device_mib_after_large_query": round(after_large / 2**20, 2),
            "device_mib_after_trim": round(trimmed / 2**20, 2), "freed_mib": round(freed / 2**20, 2),
            "query_wall_ms_before": round(_median(before), 4), "first_query_wall_ms_after": round(first_query, 4),
            "answers_identical": bool(np.array_equal(answers["before"], answers["after"])),
            "first_update_after_wall_ms": round(first_walls[0], 4),
            "first_update_after_gpu_ms": round(first_stages[0]["total"], 4),
            "update_wall_ms": round(_median(walls), 4), "update_gpu_ms": round(_median([s["total"] for s in stages]), 4),
            "trims": field.stats()["trims"]}


def print_trim(trim: dict) -> None:
    print_table(f"trim (an idle object gives back what only later frames and queries use), depth {trim['depth']}",
                ["MiB after frames", f"after a query of {trim['large_query_points']:,} points", "after the trim",
                 "freed MiB", f"query ms ({trim['query_points']:,} points)", "first query after ms",
                 "same answers", "first update after wall / device ms", "updates then wall / device ms"],
                [[trim["device_mib_after_frames"], trim["device_mib_after_large_query"], trim["device_mib_after_trim"],
                  trim["freed_mib"], trim["query_wall_ms_before"], trim["first_query_wall_ms_after"],
                  trim["answers_identical"], f"{trim['first_update_after_wall_ms']} / {trim['first_update_after_gpu_ms']}",
                  f"{trim['update_wall_ms']} / {trim['update_gpu_ms']}"]])


def measure_dense_baseline(vertices, faces, *, device: str, repeat: int, resolution: int = 129) -> dict:
    """wp.Mesh (default BVH) + mesh_query_point_sign_normal at every point of a resolution^3 grid."""
    import warp as wp

    @wp.kernel(enable_backward=False)
    def dense_grid(mesh: wp.uint64, origin: wp.vec3, step: float, n: int, out: wp.array(dtype=wp.float32)):
        i = wp.tid()
        x = i // (n * n)
        y = (i // n) % n
        z = i % n
        p = origin + wp.vec3(float(x), float(y), float(z)) * step
        q = wp.mesh_query_point_sign_normal(mesh, p, 1.0e30)
        d = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
        out[i] = wp.where(q.sign < 0.0, -d, d)

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    side = float(np.max(hi - lo)) * 1.2
    origin = wp.vec3(*((lo + hi) / 2 - side / 2))
    step = side / (resolution - 1)
    points = wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=device)
    indices = wp.array(faces.reshape(-1), dtype=wp.int32, device=device)
    grid = wp.zeros(resolution**3, dtype=wp.float32, device=device)
    holder = {}

    def build(_):
        holder["mesh"] = wp.Mesh(points=points, indices=indices)

    def query(_):
        wp.launch(dense_grid, dim=resolution**3, inputs=[holder["mesh"].id, origin, step, resolution], outputs=[grid],
                  device=device)

    build(0)
    query(0)
    builds = _time_wall(build, device, repeat)
    queries = _time_wall(query, device, repeat)
    # its accuracy at grid points spread over the grid (Warp's sign is its own, not the winding number's)
    picked = np.random.default_rng(0).choice(resolution**3, size=min(ORACLE_SAMPLE, resolution**3), replace=False)
    index = np.stack([picked // resolution**2, (picked // resolution) % resolution, picked % resolution], axis=1)
    at = ((lo + hi) / 2 - side / 2).astype(np.float64) + index * step  # as the kernel's points, in float64
    return {
        "resolution": resolution,
        "build_ms": round(_median(builds), 4),
        "query_ms": round(_median(queries), 4),
        "grid_bytes": resolution**3 * 4,
        "grid_vs_oracle": errors_against(grid.numpy()[picked], signed_distance(at, vertices, faces), vertices),
    }


def measure_allocations(vertices, faces, *, device: str, depth: int, frames: int = 5) -> dict | None:
    """Device memory the CUDA allocator holds for each side, counted by the allocator itself (Warp's
    internal allocations, such as wp.Mesh's BVH or a sort's scratch, included): a DistanceField after a few
    coherent frames, against the dense baseline's vertices, indices, wp.Mesh and (2^depth + 1)^3 grid. None on the CPU
    or without a memory pool, where the allocator keeps no such count."""
    import gc

    import warp as wp

    from badf.server.adf import DistanceField

    d = wp.get_device(device)
    if not d.is_cuda or not wp.is_mempool_enabled(d):
        return None

    def in_use() -> int:
        gc.collect()
        wp.synchronize_device(d)
        return int(wp.get_mempool_used_mem_current(d))

    before = in_use()
    field = DistanceField(vertices, faces, depth=depth, device=device)
    for k in range(1, frames + 1):
        field.update(deform(vertices, 0.02 * k))
    field_allocated = in_use() - before
    counted = field.stats()["device_bytes"]
    del field

    before = in_use()
    points = wp.array(vertices, dtype=wp.vec3, device=device)
    indices = wp.array(faces.reshape(-1), dtype=wp.int32, device=device)
    mesh = wp.Mesh(points=points, indices=indices)
    grid = wp.zeros(((1 << depth) + 1) ** 3, dtype=wp.float32, device=device)
    baseline_allocated = in_use() - before
    del mesh, grid, points, indices
    return {"field_allocated_bytes": field_allocated, "field_counted_bytes": counted,
            "dense_baseline_allocated_bytes": baseline_allocated}


def measure_traversals(field, vertices, faces, *, device: str, repeat: int) -> dict:
    """Nearest-face search at the field's corners: this engine's BVH (the 4-wide view the searches walk; the
    binary tree's own boxes were dropped on 2026-11-28) against Warp's wp.Mesh BVH (mesh_query_point_no_sign),
    each from no bound and from the bound of the corner's known nearest face (what coherence gives). Distances
    only, no sign; mismatches are counted against the engine's search without a bound."""
    import warp as wp

    from badf.server.adf._bvh import UNLIMITED_VISITS, BvhView, leaf_distance_sq, nearest_leaf_wide

    def engine_search(nearest_leaf):
        def ours(bvh: BvhView, points: wp.array(dtype=wp.vec3), seeds: wp.array(dtype=wp.int32), use_seed: int,
                 out: wp.array(dtype=wp.float32)):
            i = wp.tid()
            p = points[i]
            best = int(-1)
            best_sq = float(3.0e38)
            if use_seed != 0:
                best = seeds[i]
                best_sq = leaf_distance_sq(bvh, best, p)
            leaf, d_sq, finished = nearest_leaf(bvh, p, best, best_sq, UNLIMITED_VISITS)
            out[i] = wp.sqrt(d_sq)

        return wp.kernel(ours, name=f"traversal_{nearest_leaf.key}", enable_backward=False, module="unique")

    wide = engine_search(nearest_leaf_wide)

    @wp.kernel(enable_backward=False)
    def warps(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), bound: wp.array(dtype=wp.float32), use_seed: int,
              out: wp.array(dtype=wp.float32)):
        i = wp.tid()
        p = points[i]
        max_dist = float(1.0e30)
        if use_seed != 0:
            max_dist = bound[i] * 1.0001 + 1.0e-30
        q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
        if q.result:
            out[i] = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
        else:
            out[i] = bound[i]

    positions, values, nearest_faces = field.corner_samples()
    domain = field._domain  # both searches run in the engine's local coordinates
    local = domain.to_local(positions)
    points = wp.array(local, dtype=wp.vec3, device=device)
    leaf_of_face = np.empty(len(faces), np.int32)
    leaf_of_face[field._bvh.leaf_faces()] = np.arange(len(faces), dtype=np.int32)
    seeds = wp.array(leaf_of_face[nearest_faces], dtype=wp.int32, device=device)
    bound = wp.array(np.abs(values * domain.scale).astype(np.float32), dtype=wp.float32, device=device)
    mesh = wp.Mesh(points=wp.array(domain.to_local(vertices), dtype=wp.vec3, device=device),
                   indices=wp.array(faces.reshape(-1), dtype=wp.int32, device=device))
    bvh = field._bvh.view()
    n = len(local)
    results = {}
    out = {"corners": n}
    for name, kernel, first in (("engine_wide", wide, bvh), ("warp_mesh", warps, mesh.id)):
        for use_seed in (0, 1):
            d = wp.zeros(n, dtype=wp.float32, device=device)
            launch = lambda _: wp.launch(kernel, dim=n, inputs=[first, points, bound if kernel is warps else seeds,
                                                                 use_seed], outputs=[d], device=device)
            launch(0)
            label = f"{name}_{'bounded' if use_seed else 'unbounded'}_ms"
            out[label] = round(_median(_time_wall(launch, device, repeat)), 4)
            results[label] = d.numpy()
    reference = results["engine_wide_unbounded_ms"]
    for label, d in results.items():
        out[label.replace("_ms", "_mismatches")] = int(np.sum(np.abs(d - reference) > 1e-6 * (1 + np.abs(reference))))
    return out


def measure_search_split(vertices, faces, *, depth: int, device: str, repeat: int,
                         budgets=(64, 128, 256, 512), levels=(4, 6, 8), groups: int = 4096) -> dict:
    """The corner stage with long searches shared out (SearchSplit) and without, at one depth: per setting,
    the median time of the distance stage over coherent frames, how many corners ran past the budget, and
    how the values compare with the unsplit searches' on one common frame (bit mismatches, the largest
    difference over the bounding-box diagonal, sign flips)."""
    from badf.server.adf import DistanceField
    from badf.server.adf._distance import SearchSplit

    field = DistanceField(vertices, faces, depth=depth, device=device)
    corners = field._corners
    diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    settings = [(0, 1, 1)] + [(b, k, groups) for b in budgets for k in levels]
    frames = [deform(vertices, 0.5 + 0.02 * k) for k in range(repeat + 1)]
    check = deform(vertices, 0.9)
    rows, reference = [], None
    for budget, level, group_count in settings:
        corners.split = SearchSplit(budget, level, group_count)
        field.update(frames[0])
        times = []
        for frame in frames[1:]:
            field.update(frame)
            times.append(field.stats()["times_ms"]["distances"])
        field.update(check)
        _, values, nearest = field.corner_samples()
        if reference is None:
            reference = (values, nearest)
        rows.append({
            "budget": budget, "levels": level, "groups": group_count,
            "distances_ms": round(_median(times), 4),
            "long_corners": corners.long_searches(),
            "value_mismatches": int(np.sum(values != reference[0])),
            "max_difference_diag": float(np.max(np.abs(np.abs(values) - np.abs(reference[0])))) / diag,
            "sign_flips": int(np.sum(np.sign(values) != np.sign(reference[0]))),
            "face_differences": int(np.sum(nearest != reference[1])),
        })
    return {"depth": depth, "corners": int(field._octree.corner_count), "settings": rows}


def measure_far_corners(vertices, faces, *, depth: int, device: str, repeat: int,
                        cells=(0, 4, 6, 8, 12, 16)) -> dict:
    """Coherent updates with corners far from the surface searched by subtree beside the others
    (CornerField.far_cells K: starting bound of K finest cells or more; 0: off), at one depth: per K, the
    median device time of the distance stage and of the whole update over `repeat` frames (replayed from
    a graph), how many corners were listed far, and how the values compare with K = 0's on one common
    frame (bit mismatches, largest difference over the diagonal, sign flips, nearest-face differences)."""
    from badf.server.adf import DistanceField

    field = DistanceField(vertices, faces, depth=depth, device=device)
    corners = field._corners
    diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    frames = [deform(vertices, 0.5 + 0.02 * k) for k in range(repeat + 3)]
    check = deform(vertices, 0.9)
    rows, reference = [], None
    for far in cells:
        corners.far_cells = far
        stage, total = [], []
        for k, frame in enumerate(frames):
            field.update(frame)
            if k >= 3:  # after the eager frame and the capture
                times = field.stats()["times_ms"]
                stage.append(times["distances"])
                total.append(times["total"])
        field.update(check)
        _, values, nearest = field.corner_samples()
        if reference is None:
            reference = (values, nearest)
        listed = corners.far_corners()
        rows.append({
            "far_cells": far,
            "distances_ms": round(_median(stage), 4),
            "update_gpu_ms": round(_median(total), 4),
            "far_corners": int(listed),
            "value_mismatches": int(np.sum(values != reference[0])),
            "max_difference_diag": float(np.max(np.abs(np.abs(values) - np.abs(reference[0])))) / diag,
            "sign_flips": int(np.sum(np.sign(values) != np.sign(reference[0]))),
            "face_differences": int(np.sum(nearest != reference[1])),
        })
    return {"depth": depth, "corners": int(field._octree.corner_count), "sign": field.info()["sign"],
            "settings": rows}


def measure_kernels(vertices, faces, *, depth: int, device: str, repeat: int) -> dict:
    """Where a default coherent update's device time goes, kernel by kernel (Warp's CUDA activity timing):
    per kernel or copy, its launches and summed device time over `repeat` updates, and the span of each
    update against the time its kernels and copies were busy (the rest is the device waiting on the host)."""
    import warp as wp
    from badf.server.adf import DistanceField

    field = DistanceField(vertices, faces, depth=depth, device=device)
    frames = [deform(vertices, 0.5 + 0.02 * k) for k in range(repeat + 1)]
    graph_spans, graph_walls = [], []
    for frame in frames:
        start = time.perf_counter()
        field.update(frame)
        graph_walls.append((time.perf_counter() - start) * 1e3)
        graph_spans.append(field.stats()["times_ms"]["total"])
    field.use_graphs = False  # kernel by kernel: a graph's launch is timed as one activity
    field.update(frames[0])
    busy, spans, walls = [], [], []
    per_name: dict[str, list[float]] = {}
    for frame in frames[1:]:
        wp.synchronize_device(device)
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        start = time.perf_counter()
        field.update(frame)
        wp.synchronize_device(device)
        walls.append((time.perf_counter() - start) * 1e3)
        results = wp.timing_end()
        spans.append(field.stats()["times_ms"]["total"])
        busy.append(sum(r.elapsed for r in results))
        for r in results:
            per_name.setdefault(r.name, []).append(r.elapsed)
    rows = sorted(((name, len(t) / repeat, sum(t) / repeat) for name, t in per_name.items()), key=lambda r: -r[2])
    return {
        "depth": depth,
        "updates": repeat,
        "update_wall_ms": round(_median(walls), 4),
        "update_span_ms": round(_median(spans), 4),
        "busy_ms": round(_median(busy), 4),
        "graph_update_wall_ms": round(_median(graph_walls[3:] or graph_walls), 4),
        "graph_update_span_ms": round(_median(graph_spans[3:] or graph_spans), 4),
        "graph_captures": field.stats()["graph_captures"],
        "launches_per_update": round(sum(r[1] for r in rows), 1),
        "activities": [{"name": n, "per_update": round(c, 2), "ms_per_update": round(t, 4)} for n, c, t in rows],
    }


def _corner_kernel_ms(field, frames, device: str) -> tuple[float, float, float]:
    """Median device time (ms) of the corner searches, of the corner signs (their kernels' CUDA activity
    timing) and of the whole distance stage (its events: with winding numbers beside the searches, the
    two kernels overlap) over frames[1:], after frames[0] settles the field's sizes."""
    import warp as wp

    field.update(frames[0])
    searches, signs, stage = [], [], []
    for frame in frames[1:]:
        wp.synchronize_device(device)
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        field.update(frame)
        results = wp.timing_end()
        searches.append(sum(r.elapsed for r in results if "corner_searches" in r.name))
        signs.append(sum(r.elapsed for r in results if "sign_corners" in r.name))
        stage.append(field.stats()["times_ms"]["distances"])
    return round(_median(searches), 4), round(_median(signs), 4), round(_median(stage), 4)


def measure_block_dims(vertices, faces, *, depth: int, device: str, repeat: int, dims=(32, 64, 128, 256)) -> dict:
    """Device time of the corner searches, the corner signs and the distance stage for each threads-per-block
    choice (over `repeat` coherent updates, kernels launched one by one)."""
    from badf.server.adf import DistanceField
    from badf.server.adf import _distance

    field = DistanceField(vertices, faces, depth=depth, device=device)
    field.use_graphs = False
    frames = [deform(vertices, 0.5 + 0.02 * k) for k in range(repeat + 1)]
    default = (_distance.SEARCH_BLOCK_DIM, _distance.SIGN_BLOCK_DIM)
    rows = []
    try:
        for dim in dims:
            _distance.SEARCH_BLOCK_DIM = _distance.SIGN_BLOCK_DIM = dim
            searches_ms, signs_ms, distances_ms = _corner_kernel_ms(field, frames, device)
            rows.append({"block_dim": dim, "searches_ms": searches_ms, "signs_ms": signs_ms,
                         "distances_ms": distances_ms})
    finally:
        _distance.SEARCH_BLOCK_DIM, _distance.SIGN_BLOCK_DIM = default
    return {"depth": depth, "corners": field.stats()["counts"]["unique_corners"], "rows": rows}


def measure_register_caps(vertices, faces, *, depth: int, device: str, repeat: int,
                          caps=(32, 40, 48, 64, 96, 128, 255)) -> dict:
    """Registers and local memory per thread of the corner searches and the costly corner-sign kernel (the
    winding numbers where the sign is by winding number), each compiled with a cap on registers per thread
    while the other stays as the engine compiles it, and the device time of both and of the distance stage
    (over `repeat` coherent updates, kernels launched one by one): whether occupancy limits them."""
    import warp as wp
    from badf.server.adf import DistanceField
    from badf.server.adf import _distance
    from badf.server.adf._sign import _SIGN_CODES, SIGN_WINDING

    field = DistanceField(vertices, faces, depth=depth, device=device)
    field.use_graphs = False
    method = _SIGN_CODES[field.info()["sign"]]
    frames = [deform(vertices, 0.5 + 0.02 * k) for k in range(repeat + 1)]
    sign_key = ("winding", method) if method == SIGN_WINDING else ("sign", method)
    engines = (_distance.corner_searches,
               _distance.winding_kernel() if method == SIGN_WINDING else _distance.sign_kernel(method))

    def capped(kernel, cap):
        return wp.kernel(kernel.func, enable_backward=False, cuda_max_registers=cap, module="unique",
                         name=f"{kernel.key}_cap{cap}")

    choices = [(None, None)] + [(cap, None) for cap in caps] + [(None, cap) for cap in caps]
    rows = []
    try:
        for search_cap, sign_cap in choices:
            variants = (engines[0] if search_cap is None else capped(engines[0], search_cap),
                        engines[1] if sign_cap is None else capped(engines[1], sign_cap))
            _distance.corner_searches, _distance._KERNELS[sign_key] = variants
            searches_ms, signs_ms, distances_ms = _corner_kernel_ms(field, frames, device)
            properties = [wp.get_cuda_kernel_properties(k, device, block_dim=_distance.SEARCH_BLOCK_DIM) for k in variants]
            rows.append({"searches_cap": search_cap, "signs_cap": sign_cap, "searches_ms": searches_ms,
                         "searches_registers": properties[0]["register_count"],
                         "searches_local_bytes": properties[0]["local_memory_size"],
                         "signs_ms": signs_ms,
                         "signs_registers": properties[1]["register_count"],
                         "signs_local_bytes": properties[1]["local_memory_size"],
                         "distances_ms": distances_ms})
    finally:
        _distance.corner_searches, _distance._KERNELS[sign_key] = engines
    return {"depth": depth, "corners": field.stats()["counts"]["unique_corners"], "sign": field.info()["sign"],
            "rows": rows}


def print_kernels(profile: dict) -> None:
    print_table(
        f"device activity of one coherent update, depth {profile['depth']}, mean over {profile['updates']} updates",
        ["activity", "per update", "ms per update"],
        [[a["name"], a["per_update"], a["ms_per_update"]] for a in profile["activities"]],
    )
    print(f"update: wall {profile['update_wall_ms']} ms, stage span {profile['update_span_ms']} ms, "
          f"device busy {profile['busy_ms']} ms, {profile['launches_per_update']} activities per update")
    print(f"replayed from a CUDA graph: wall {profile['graph_update_wall_ms']} ms, "
          f"span {profile['graph_update_span_ms']} ms ({profile['graph_captures']} captures)")


def print_search_split(sweep: dict) -> None:
    print_table(
        f"corner searches shared out, depth {sweep['depth']}, {sweep['corners']} corners: distance stage median ms",
        ["budget", "levels", "groups", "distances ms", "long corners", "bit mismatches", "max diff / diag",
         "sign flips", "face diffs"],
        [[f"{v:.2g}" if isinstance(v, float) and k == "max_difference_diag" else v for k, v in row.items()]
         for row in sweep["settings"]],
    )


def _write_part(args: argparse.Namespace, benchmark: str, device: str, faces, results: dict) -> None:
    """Write one of the single-part runs (--kernels, --far-sweep, --split-sweep, --sign-sweep) as JSON, where --out asks."""
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"benchmark": benchmark, "date": timestamp(), "device": bench_device_name(device),
                       "mesh": {"path": args.mesh, "faces": len(faces)}, **results}, f, indent=1)


def run(args: argparse.Namespace) -> int:
    # flags that would be run as if absent
    if (args.block_sweep or args.register_sweep) and not args.kernels:
        raise BenchFlagError("--block-sweep and --register-sweep go with --kernels")
    device = start_warp(args.device)
    if args.kernels and not device.startswith("cuda"):
        raise BenchFlagError("--kernels profiles CUDA activity; give a CUDA --device")
    vertices, faces = read_mesh(args.mesh)
    repeat = args.repeat
    if args.kernels:
        profile = measure_kernels(vertices, faces, depth=args.depth, device=device, repeat=repeat)
        print_kernels(profile)
        if args.block_sweep:
            blocks = measure_block_dims(vertices, faces, depth=args.depth, device=device, repeat=repeat)
            profile["block_dims"] = blocks
            print_table(f"corner kernels by threads per block, depth {blocks['depth']}, {blocks['corners']} corners",
                        ["block dim", "searches ms", "signs ms", "distance stage ms"],
                        [[r["block_dim"], r["searches_ms"], r["signs_ms"], r["distances_ms"]] for r in blocks["rows"]])
        if args.register_sweep:
            caps = measure_register_caps(vertices, faces, depth=args.depth, device=device, repeat=repeat)
            profile["register_caps"] = caps
            print_table(f"corner kernels by cap on registers per thread, depth {caps['depth']}, {caps['corners']} "
                        f"corners, sign {caps['sign']}",
                        ["searches cap", "searches ms", "registers", "local bytes", "signs cap", "signs ms", "registers",
                         "local bytes", "distance stage ms"],
                        [[r["searches_cap"] or "engine's", r["searches_ms"], r["searches_registers"],
                          r["searches_local_bytes"], r["signs_cap"] or "engine's", r["signs_ms"], r["signs_registers"],
                          r["signs_local_bytes"], r["distances_ms"]] for r in caps["rows"]])
        _write_part(args, "engine-kernels", device, faces, profile)
        return 0
    if args.far_sweep:
        sweeps = []
        for depth in args.far_sweep:
            sweep = measure_far_corners(vertices, faces, depth=depth, device=device, repeat=repeat)
            sweeps.append(sweep)
            print_table(f"far corners searched beside, depth {depth}, {sweep['corners']} corners, sign {sweep['sign']}:"
                        f" medians of {repeat}",
                        ["far cells", "distances ms", "update gpu ms", "far corners", "bit mismatches",
                         "max diff / diag", "sign flips", "face diffs"],
                        [[r["far_cells"], r["distances_ms"], r["update_gpu_ms"], r["far_corners"], r["value_mismatches"],
                          f"{r['max_difference_diag']:.2g}", r["sign_flips"], r["face_differences"]]
                         for r in sweep["settings"]])
        _write_part(args, "engine-far-corners", device, faces, {"repeat": repeat, "sweeps": sweeps})
        return 0
    if args.sign_sweep:
        rows, results = [], []
        for sign in ("auto", "pseudonormal", "winding", "none"):
            result = measure_field(vertices, faces, device=device, repeat=repeat, depth=args.depth, sign=sign)
            info = result.pop("field").info()
            result.pop("vertices")
            result.update(sign_resolved=info["sign"], parts_overlap=info["parts_overlap"])
            results.append(result)
            stages = result["update_stages_ms"]
            rows.append([sign, info["sign"], result["update_gpu_ms"], result["update_wall_ms"], stages.get("normals", 0.0),
                         stages.get("distances", 0.0), result["build_gpu_ms"]])
        print_table(f"updates by sign, depth {args.depth}, {args.mesh} ({len(faces)} triangles), median of {repeat}; "
                    "with auto on a closed mesh the distance stage holds the check for parts running into each other "
                    "(beside the searches on CUDA)", ["sign", "resolved", "update device ms", "update wall ms", "normals ms",
                                    "distances ms", "build device ms"], rows)
        _write_part(args, "engine-signs", device, faces, {"repeat": repeat, "depth": args.depth, "signs": results})
        return 0
    if args.split_sweep:
        sweeps = []
        for depth in args.split_sweep:
            sweeps.append(measure_search_split(vertices, faces, depth=depth, device=device, repeat=repeat))
            print_search_split(sweeps[-1])
        _write_part(args, "engine-search-split", device, faces, {"repeat": repeat, "sweeps": sweeps})
        return 0
    report = {
        "benchmark": "engine",
        "date": timestamp(),
        "device": bench_device_name(device),
        "host": platform.node(),
        "mesh": {"path": args.mesh, "vertices": len(vertices), "faces": len(faces)},
        "repeat": repeat,
        "configurations": [],
    }
    configs = [{"depth": args.depth} | ({"bvh": args.bvh} if args.bvh != "auto" else {})]
    rows, region_rows = [], []
    for options in configs:  # the full run's rows join the list once the main configuration has run
        result = measure_field(vertices, faces, device=device, repeat=repeat, **options)
        field, current = result.pop("field"), result.pop("vertices")
        if options == configs[0]:
            result.update(measure_queries(field, current, faces, device=device, repeat=repeat))
            result["traversal"] = measure_traversals(field, current, faces, device=device, repeat=repeat)
            if not args.quick:
                other_shape = "morton" if field.info()["bvh"] == "sah" else "sah"
                configs += _switches(args.depth, vertices, other_shape=other_shape)
        if "region" in options:  # what the region costs queries (exact outside it), and their accuracy
            result.update(measure_queries(field, current, faces, device=device, repeat=repeat))
            region_rows.append(result)
        report["configurations"].append(result)
        rows.append([
            ", ".join("region=a quarter of the box" if k == "region" else f"{k}={v:.4g}" if isinstance(v, float)
                      else f"{k}={v}" for k, v in options.items()),
            result["build_gpu_ms"], result["build_wall_ms"], result["update_gpu_ms"], result["update_wall_ms"],
            result["moving_update_gpu_ms"], result["moving_update_wall_ms"], result["counts"]["unique_corners"], round(result["device_bytes"] / 2**20, 2),
        ])
        del field
    # the dense grid of the octree's finest lattice: 129^3 at depth 7, the baseline
    lattice = (1 << args.depth) + 1
    baseline = measure_dense_baseline(vertices, faces, device=device, repeat=repeat, resolution=lattice)
    report["dense_baseline"] = baseline
    report["allocations"] = measure_allocations(vertices, faces, device=device, depth=args.depth)
    report["rigid"] = measure_rigid(vertices, faces, device=device, depth=args.depth, repeat=repeat)
    report["violent"] = measure_violent(vertices, faces, device=device, depth=args.depth, repeat=repeat)
    report["trim"] = measure_trim(vertices, faces, device=device, depth=args.depth, repeat=repeat)
    first = report["configurations"][0]
    print_table(
        f"engine on {report['device']}, {args.mesh} ({len(faces)} triangles), median of {repeat}",
        ["options", "build device ms", "build wall ms", "update device ms", "update wall ms", "moving device ms",
         "moving wall ms", "corners", "MiB"],
        rows,
    )
    print("memory of the first configuration (bytes):", first["memory_bytes"])
    print("traversal at the corners (ms):", first["traversal"])
    print("stages of the first configuration, update (ms):", first["update_stages_ms"])
    print(f"stages of the first configuration, build (ms; {first['builds_measured']} of {repeat} first frames measured, "
          "the rest planned from the area):", first["build_stages_ms"])
    print(f"stages of the first configuration, frames that move the domain (ms; {first['moving_domain_moves']} moves, "
          f"{first['moving_measured_frames']} measured frames):", first["moving_update_stages_ms"])
    adf, exact, grid = first["adf_vs_oracle"], first["exact_vs_oracle"], baseline["grid_vs_oracle"]
    print(f"queries of 65,536 points: adf {first['query_adf_ms']} ms, exact {first['query_exact_ms']} ms;"
          f" adf vs exact max error {first['adf_vs_exact_max_error_diag']:.2e} diag")
    print(f"  against the float64 oracle at {adf['points']} of them (max / mean, diagonals): adf "
          f"{adf['max_error_diag']:.2e} / {adf['mean_error_diag']:.2e}, exact {exact['max_error_diag']:.2e} / "
          f"{exact['mean_error_diag']:.2e}")
    for row in region_rows:
        adf = row["adf_vs_oracle"]
        print(f"  with a region of interest (a quarter of the box; queries outside it exact): adf {row['query_adf_ms']} "
              f"ms, against the oracle {adf['max_error_diag']:.2e} / {adf['mean_error_diag']:.2e} diagonals")
    print(f"dense baseline ({baseline['resolution']}^3 grid, wp.Mesh + mesh_query_point_sign_normal): "
          f"build {baseline['build_ms']} ms, query {baseline['query_ms']} ms, grid {baseline['grid_bytes'] / 2**20:.2f} MiB;"
          f" against the oracle at {grid['points']} grid points {grid['max_error_diag']:.2e} / "
          f"{grid['mean_error_diag']:.2e} diagonals (max / mean)")
    if report["allocations"] is not None:
        a = report["allocations"]
        print(f"device memory held, by the allocator's count: the field {a['field_allocated_bytes'] / 2**20:.2f} MiB "
              f"(its own count {a['field_counted_bytes'] / 2**20:.2f}); the dense baseline "
              f"{a['dense_baseline_allocated_bytes'] / 2**20:.2f} MiB (wp.Mesh, its inputs and the grid)")
    print_rigid(report["rigid"])
    print_violent(report["violent"])
    print_trim(report["trim"])
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(report, handle, indent=2)
        print("wrote", args.out)
    return 0


def _switches(depth: int, vertices: np.ndarray, *, other_shape: str) -> list[dict]:
    """The full run's configurations beside the main one: each switch, then the other depths."""
    return [
        {"depth": depth, "bvh": other_shape},
        {"depth": depth, "graphs": False},
        {"depth": depth, "one_stream": True},
        {"depth": depth, "coherence": False},
        {"depth": depth, "sign": "pseudonormal"},
        {"depth": depth, "sign": "none"},
        {"depth": depth, "band": float(np.linalg.norm(vertices.max(0) - vertices.min(0))) * 0.02},
        {"depth": depth, "halo": 0},
        {"depth": depth, "refine": "centroid", "halo": 0},
        {"depth": depth, "region": quarter_of_the_box(vertices)},
    ] + [{"depth": d} for d in range(5, 10) if d != depth]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mesh", required=True, help=MESH_HELP)
    parser.add_argument("--device", default=None, help="cpu, cuda:0, ... (default: the first GPU, else cpu)")
    parser.add_argument("--depth", type=int, default=7, help="octree depth of the main configuration")
    parser.add_argument("--repeat", type=int, default=20, help="timed repeats per measurement")
    parser.add_argument("--quick", action="store_true", help="only the main configuration")
    parser.add_argument("--bvh", choices=BVH_SHAPES, default="auto",
                        help="the BVH's shape in the main configuration (default: the engine's, sah on the CPU and "
                             "morton on CUDA; the other one is a row of the full run)")
    parser.add_argument("--far-sweep", type=int, nargs="+", metavar="DEPTH",
                        help="only time updates with far corners searched by subtree beside the others, at these "
                             "depths, against off")
    parser.add_argument("--split-sweep", type=int, nargs="+", metavar="DEPTH",
                        help="only time the corner stage with long searches shared out or not, at these depths")
    parser.add_argument("--sign-sweep", action="store_true",
                        help="only time builds and updates under each sign method (auto, pseudonormal, winding, none)")
    parser.add_argument("--kernels", action="store_true",
                        help="only profile a default update kernel by kernel (CUDA activity timing)")
    parser.add_argument("--block-sweep", action="store_true",
                        help="with --kernels: also time the corner kernels at 32, 64, 128 and 256 threads per block")
    parser.add_argument("--register-sweep", action="store_true",
                        help="with --kernels (CUDA): also compile the corner kernels with caps on registers per "
                             "thread and time them")
    parser.add_argument("--out", default=None, help="write the full results as JSON here")


def main() -> int:
    from badf.bench._cli import main_of

    return main_of("engine")


if __name__ == "__main__":
    raise SystemExit(main())
