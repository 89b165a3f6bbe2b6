"""What the probes share: a coherent update of a mesh at depth 7 whose corner-search launch is captured,
so a probe can launch its own variant of the search over exactly the engine's inputs."""

import argparse
import cProfile
import io
import pstats
import sys
import time

import numpy as np
import warp as wp

from badf.server.adf import DistanceField
from badf.server.adf import _distance

# corner_searches' inputs up to its budget; after it come the budget, `seeded` and the seeds
SEEDING_INPUTS = [arg.label for arg in _distance.corner_searches.adj.args].index("budget")


def captured_search(path: str, device: str):
    """(field, the corner search's inputs before its budget (what seeds a search), corner count, the
    engine's distances)."""
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    data = np.load(path)
    vertices, faces = data["vertices"], data["faces"]
    field = DistanceField(vertices, faces, depth=7, device=device)
    field.use_graphs = False
    field.update(vertices * np.float32(1.001))
    captured = {}
    launch = wp.launch

    def spy(kernel, *args, **kwargs):
        if kernel in (_distance.corner_searches, _distance.corner_searches_budgeted):
            captured["inputs"] = list(kwargs["inputs"])
        return launch(kernel, *args, **kwargs)

    wp.launch = spy
    try:
        field.update(vertices * np.float32(1.002))
    finally:
        wp.launch = launch
    inputs = captured["inputs"][:SEEDING_INPUTS]
    if wp.get_device(device).is_cpu:
        # the CPU's searches are launched in chunks (launch_per_item), so the keys and count captured are the last
        # chunk's: take the whole frame's
        octree = field._octree
        inputs[0], inputs[1], inputs[2] = octree.corner_keys, octree.corner_set.view.count, octree.corner_capacity
    count = int(inputs[1].numpy()[0])
    return field, inputs, count, np.abs(field._corners.value.numpy()[:count])


def device_times(launches, device: str, repeats: int) -> tuple[float, float]:
    """(median, least) ms of `launches()`: device time between two events on CUDA, wall time on the CPU."""
    times = []
    for _ in range(repeats):
        wp.synchronize()
        if device != "cpu":
            start, end = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
            wp.record_event(start)
        else:
            started = time.perf_counter()
        launches()
        if device != "cpu":
            wp.record_event(end)
            wp.synchronize()
            times.append(wp.get_event_elapsed_time(start, end))
        else:
            times.append((time.perf_counter() - started) * 1e3)
    return float(np.median(times)), float(np.min(times))


def engine_search(inputs: list, capacity: int, distance: wp.array, nearest: wp.array, device: str):
    """A launcher of the engine's corner searches over the captured inputs, every corner searched whole."""
    dummy = wp.zeros(1, dtype=int, device=device)
    dummy64 = wp.zeros(1, dtype=wp.int64, device=device)

    def launch():
        wp.launch(_distance.corner_searches, dim=capacity,
                  inputs=inputs + [_distance.UNLIMITED_VISITS, 0, dummy, dummy],
                  outputs=[distance, nearest, dummy, dummy, dummy64, dummy64], device=device,
                  block_dim=_distance.SEARCH_BLOCK_DIM)

    return launch


def alternating_parser(doc: str) -> argparse.ArgumentParser:
    """The options of a probe that alternates two ways of building over meshes (probe_first_plan, probe_reserve)."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--mesh", nargs="+", required=True)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--device", default=None)
    parser.add_argument("--out")
    return parser


def quartiles(values: list[float]) -> list[float]:
    q = np.percentile(np.asarray(values, float), [25, 50, 75])
    return [round(float(q[0]), 4), round(float(q[1]), 4), round(float(q[2]), 4)]


def fmt_quartiles(q: list[float]) -> str:
    return f"{q[1]:.3f} [{q[0]:.3f}, {q[2]:.3f}]"


def constructor_profile(vertices, faces, device: str, *, own: int, cumulative: int) -> str:
    """Where one DistanceField constructor's host time goes (cProfile): the `own` functions with the most time of
    their own, then the `cumulative` with the most in all."""
    profile = cProfile.Profile()
    profile.enable()
    DistanceField(vertices, faces, device=device)
    wp.synchronize_device(device)
    profile.disable()
    text = io.StringIO()
    stats = pstats.Stats(profile, stream=text)
    stats.sort_stats("tottime").print_stats(own)
    stats.sort_stats("cumulative").print_stats(cumulative)
    return text.getvalue()


def timed_constructions(vertices, faces, device: str, count: int) -> tuple[list[float], list[dict]]:
    """`count` new DistanceFields, each timed by the wall clock with the device synchronised before and after:
    (wall ms, each one's per-stage times)."""
    walls, stages = [], []
    for _ in range(count):
        wp.synchronize_device(device)
        start = time.perf_counter()
        field = DistanceField(vertices, faces, device=device)
        wp.synchronize_device(device)
        walls.append((time.perf_counter() - start) * 1e3)
        stages.append(field.stats()["times_ms"])
        del field
    return walls, stages


def mesh_device_out() -> tuple[str, str, str | None]:
    """A probe's command line, `MESH.npz [device] [--out FILE]`: (mesh path, device, default cuda:0; --out or
    None)."""
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    out = sys.argv[sys.argv.index("--out") + 1] if "--out" in sys.argv else None
    if out in args:
        args.remove(out)
    return args[0], (args[1] if len(args) > 1 else "cuda:0"), out
