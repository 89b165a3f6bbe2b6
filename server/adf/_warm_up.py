"""Load every kernel the engine launches on a device before the first real object needs it.

Warp compiles a module on its first launch on a device (seconds per module on the CPU back-end when its
kernel cache is cold) and loads it from the cache otherwise; a CUDA graph's first capture also costs more
than its replays. A server that waits for its first client to pay for this answers that client late: the
soak benchmark's slowest round trip (3.5 s against a median of 43 ms) was such a first use. `warm_up` runs
every path of the engine once on small shapes, so a worker pays before it says it is ready.
"""

from __future__ import annotations

import time

import numpy as np

from badf.server.adf._field import DistanceField
from badf.server.adf._inputs import QUERY_OUTPUTS

# A unit cube: 8 vertices, 12 outward-facing triangles (closed, so "auto" picks pseudonormals).
_CUBE_VERTICES = np.array(
    [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], dtype=np.float64
)
_CUBE_FACES = np.array(
    [
        [0, 1, 3], [0, 3, 2],  # x = -0.5
        [4, 6, 7], [4, 7, 5],  # x = +0.5
        [0, 4, 5], [0, 5, 1],  # y = -0.5
        [2, 3, 7], [2, 7, 6],  # y = +0.5
        [0, 2, 6], [0, 6, 4],  # z = -0.5
        [1, 5, 7], [1, 7, 3],  # z = +0.5
    ],
    dtype=np.int32,
)

# Frames per shape: the build (measured), then planned frames; on CUDA the second planned frame is captured
# as a graph and the third replays it.
_FRAMES = 4


def warm_up(device: str | None = None) -> float:
    """Run every engine path once on `device` (builds, planned frames, graphs, queries, slices, for each
    sign method); returns the seconds it took. Raises what the engine raises if the device is unusable."""
    started = time.perf_counter()
    open_box = _CUBE_FACES[:-2]  # without its top face: open, so "auto" picks winding numbers
    points = np.array([[0.1, 0.2, 0.3], [0.9, -0.4, 0.2], [5.0, 5.0, 5.0], [0.5, 0.0, 0.0]])
    for faces, sign in ((_CUBE_FACES, "auto"), (open_box, "auto"), (_CUBE_FACES, "none")):
        field = DistanceField(_CUBE_VERTICES, faces, depth=3, sign=sign, device=device)
        for frame in range(1, _FRAMES + 1):
            vertices = _CUBE_VERTICES * (1.0 + 0.01 * frame)
            # float32 frames are recentred on the device, float64 ones on the host: both paths run
            field.update(vertices.astype(np.float32) if frame % 2 else vertices)
        for mode in ("adf", "exact"):
            field.query(points, mode=mode, outputs=QUERY_OUTPUTS)
            field.query(points.astype(np.float32), mode=mode, outputs=("distance",))
        field.slice("z", 0.0, resolution=8)
    return time.perf_counter() - started
