"""Probe, not part of the product: where a batch query's time goes, host and device.

    python3 bench/probes/probe_query_latency.py MESH.npz [device] [--points N] [--repeat K] [--out F.json]

`badf bench engine` reads 0.3 to 1.2 ms for a 65,536-point ADF query of the bunny on H100s and H200s, where the
kernel has little to do. This splits one query's wall time into its host steps (checking the points, the far-point
pass, the copies' calls, the rest) and, on CUDA, the device's own time from events recorded around the upload, the
kernel and each download. Each row is the median of K queries after warm-up, for ADF and exact mode with the
distance alone and with all four outputs.
"""

import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

from badf.server.adf import DistanceField
from badf.server.adf import _distance, _field

parser = argparse.ArgumentParser()
parser.add_argument("mesh")
parser.add_argument("device", nargs="?", default="cuda:0")
parser.add_argument("--points", type=int, default=65_536)
parser.add_argument("--repeat", type=int, default=30)
parser.add_argument("--depth", type=int, default=7)
parser.add_argument("--out")
parser.add_argument("--profile", action="store_true", help="also print cProfile's top functions of ADF queries")
args = parser.parse_args()

wp.init()
mesh = np.load(args.mesh)
vertices, faces = mesh["vertices"].astype(np.float32), mesh["faces"].astype(np.int32)
field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
device = wp.get_device(args.device)
lo, hi = vertices.min(axis=0), vertices.max(axis=0)
points = np.random.default_rng(0).uniform(lo, hi, (args.points, 3)).astype(np.float32)

# timers wrapped around the engine's own steps; each adds its host time (ms) under its name per query
spent: dict[str, float] = {}
events: list[tuple[str, object]] = []


def timed(name, function):
    def wrapper(*a, **k):
        start = time.perf_counter()
        try:
            return function(*a, **k)
        finally:
            spent[name] = spent.get(name, 0.0) + (time.perf_counter() - start) * 1e3
    return wrapper


def mark(name):
    if device.is_cuda:
        event = wp.Event(device, enable_timing=True)
        wp.record_event(event)
        events.append((name, event))


_field.as_points = timed("check points", _field.as_points)
_field._pull_far_points = timed("far-point pass", _field._pull_far_points)
real_copy, real_launch = wp.copy, _distance.launch_per_item


def copy(dest, src, *a, **k):
    mark("copy " + ("up" if dest.device.is_cuda and not src.device.is_cuda else "down" if src.device.is_cuda else "host"))
    start = time.perf_counter()
    real_copy(dest, src, *a, **k)
    spent["copy calls"] = spent.get("copy calls", 0.0) + (time.perf_counter() - start) * 1e3


def launch(*a, **k):
    mark("kernel")
    start = time.perf_counter()
    real_launch(*a, **k)
    spent["launch call"] = spent.get("launch call", 0.0) + (time.perf_counter() - start) * 1e3
    mark("after kernel")


_distance.wp.copy = copy
_distance.launch_per_item = launch
real_sync = wp.synchronize_device


def sync(*a, **k):
    mark("end")
    start = time.perf_counter()
    real_sync(*a, **k)
    spent["final wait"] = spent.get("final wait", 0.0) + (time.perf_counter() - start) * 1e3


_distance.wp.synchronize_device = sync

rows = []
print(f"{device} ({device.name}), {args.points} points, depth {args.depth}, median of {args.repeat}")
for mode in ("adf", "exact"):
    for outputs in (("distance",), ("distance", "closest_point", "normal", "face")):
        for _ in range(3):
            field.query(points, mode=mode, outputs=outputs)
        walls, host_parts, device_parts = [], {}, {}
        for _ in range(args.repeat):
            spent.clear()
            events.clear()
            real_sync(device)
            start = time.perf_counter()
            field.query(points, mode=mode, outputs=outputs)
            walls.append((time.perf_counter() - start) * 1e3)
            for name, value in spent.items():
                host_parts.setdefault(name, []).append(value)
            # device time between consecutive events, named by the first
            for (name, first), (_, second) in zip(events, events[1:]):
                if name == "after kernel":
                    name = "after kernel to first download"
                device_parts.setdefault(name, [0.0] * args.repeat)
                device_parts[name][len(walls) - 1] += wp.get_event_elapsed_time(first, second)
        row = {"mode": mode, "outputs": list(outputs), "wall_ms": statistics.median(walls),
               "host_ms": {k: statistics.median(v) for k, v in host_parts.items()},
               "device_ms": {k: statistics.median(v) for k, v in device_parts.items()}}
        accounted = sum(row["host_ms"].values())
        row["host_ms"]["rest"] = row["wall_ms"] - accounted
        rows.append(row)
        print(f"{mode:5s} {'+'.join(o[:4] for o in outputs):22s} wall {row['wall_ms']:.3f} ms")
        print("   host:   " + ", ".join(f"{k} {v:.3f}" for k, v in row["host_ms"].items()))
        if row["device_ms"]:
            print("   device: " + ", ".join(f"{k} {v:.3f}" for k, v in row["device_ms"].items()))
# the ADF kernel on the points it answers by interpolation alone, and on those it answers exactly (where its
# distance equals exact mode's to the bit: an open mesh's points across an opening, a vanished gradient, ...)
interpolated = field.query(points).distance != field.query(points, mode="exact").distance
split = {}
for name, subset in (("interpolated", points[interpolated]), ("exact fallbacks", points[~interpolated])):
    kernel_times = []
    for k in range(args.repeat + 3):
        events.clear()
        field.query(subset)
        times = dict((n, e) for n, e in events)
        if device.is_cuda and k >= 3:
            kernel_times.append(wp.get_event_elapsed_time(times["kernel"], times["after kernel"]))
    split[name] = {"points": len(subset), "kernel_ms": statistics.median(kernel_times) if kernel_times else None}
    print(f"ADF kernel on the {len(subset)} points {name}: {split[name]['kernel_ms']} ms")
if args.profile:
    import cProfile
    import pstats
    for outputs in (("distance",), ("distance", "closest_point", "normal", "face")):
        _distance.wp.copy, _distance.launch_per_item, _distance.wp.synchronize_device = real_copy, real_launch, real_sync
        profile = cProfile.Profile()
        profile.enable()
        for _ in range(args.repeat):
            field.query(points, outputs=outputs)
        profile.disable()
        print(f"cProfile, {args.repeat} ADF queries of {'+'.join(outputs)}:")
        pstats.Stats(profile).sort_stats("cumulative").print_stats(30)
if args.out:
    with open(args.out, "w") as f:
        json.dump({"device": str(device), "name": device.name, "points": args.points, "rows": rows, "adf_kernel_split": split}, f, indent=1)
