"""Reproduces a wrong first frame on CUDA: a second object built with the halo pass held to 37 threads (as
tests/test_engine.py's test_halo_pass_with_fewer_threads_than_neighbours_finds_the_same_cells does) had
1,276 of 13,910 corners wrong, 475 of them with the wrong sign, on an H200 whose kernel cache was empty
(2026-11-29). With the cache filled, or with CUDA_LAUNCH_BLOCKING=1, the same script found every corner
right. Each object's corners are compared with the float64 oracle, frame by frame.

    WARP_CACHE_PATH=$(mktemp -d) python bench/probes/probe_halo_race.py [--side-stream off] [--mempool off]

`--side-stream off` queues every object's work on its one stream and `--mempool off` turns off the stream-
ordered allocator: which of them makes the wrong frame go away says where the race is (not run). The cause was
found by reading the code (a BVH cut made after a side stream's fork, 3c7bafb); after that change this script found
every corner right on an H200 with an empty cache (docs/results/cuda-tests-h200-0830).
"""

import argparse
import pathlib
import sys
import time

import numpy as np
import warp as wp

from badf.bench._oracle import signed_distance
from badf.server.adf import DistanceField, _buffers, _octree


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--side-stream", choices=("on", "off"), default="on")
    parser.add_argument("--mempool", choices=("on", "off"), default="on")
    args = parser.parse_args()
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "tests"))
    import meshes  # the tests' meshes: spot is bundled in tests/data

    wp.config.quiet = True
    wp.init()
    _buffers.SideStream.allowed = args.side_stream == "on"
    if args.mempool == "off" and args.device.startswith("cuda"):
        wp.set_mempool_enabled(args.device, False)
    vertices, faces = meshes.load("spot")
    started = time.perf_counter()
    wide = DistanceField(vertices, faces, depth=5, halo=2, device=args.device)
    _octree._HALO_THREADS = 37
    narrow = DistanceField(vertices, faces, depth=5, halo=2, device=args.device)
    for frame in (0, 1, 2):
        moved = vertices * (1.0 + 0.01 * frame)
        if frame:
            wide.update(moved)
            narrow.update(moved)
        truth_at = {}
        row = [f"frame {frame}"]
        for name, field in (("wide", wide), ("narrow", narrow)):
            positions, values, _faces = field.corner_samples()
            key = positions.tobytes()
            if key not in truth_at:
                truth_at[key] = signed_distance(positions, moved.astype(np.float64), faces)
            truth = truth_at[key]
            error = np.abs(values - truth)
            row.append(f"{name}: {len(values)} corners, max |error| {error.max():.2e}, "
                       f"{int((error > 1e-4).sum())} over 1e-4, {int(((values < 0) != (truth < 0)).sum())} signs wrong")
        print(" | ".join(row), flush=True)
    print(f"{time.perf_counter() - started:.1f} s on {args.device}")


if __name__ == "__main__":
    main()
