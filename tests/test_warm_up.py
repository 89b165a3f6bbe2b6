"""`warm_up` loads every kernel the engine uses, so a worker's first object pays no module load.

Each case runs in a fresh Python process (a module loaded by an earlier test would hide a miss) and
counts the module loads Warp reports while it builds, updates, queries and slices objects with options
that `warm_up` does not use itself (other depths, band, coherence off, centroid refinement, halos 0 and 2,
every sign method). A second process runs the same work without warming up, which shows that the count
can fail: there the work loads modules.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

_CHILD = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    import trimesh
    import warp as wp

    wp.config.log_level = wp.LOG_INFO  # Warp reports each module load at INFO level
    wp.init()
    from badf.server.adf import DistanceField, QUERY_OUTPUTS
    from badf.server.adf._warm_up import warm_up

    device, warm = sys.argv[1], sys.argv[2] == "1"
    if warm:
        warm_up(device)
    print("---- work begins ----", flush=True)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    box = trimesh.creation.box()
    cases = [
        (sphere.vertices, sphere.faces, dict(depth=5)),
        (sphere.vertices, sphere.faces, dict(depth=4, band=0.2, coherence=False, refine="centroid", halo=0)),
        (torus.vertices, torus.faces, dict(depth=5, sign="winding", halo=2)),
        (box.vertices, box.faces[:-2], dict(depth=4, sign="none", band=0.1)),
        (box.vertices, box.faces, dict(depth=4, sign="pseudonormal")),
    ]
    rng = np.random.default_rng(7)
    for vertices, faces, options in cases:
        field = DistanceField(vertices, faces, device=device, **options)
        for frame in range(4):
            moved = vertices * (1.0 + 0.02 * frame) + 0.01 * rng.standard_normal(vertices.shape)
            field.update(moved.astype(np.float32) if frame % 2 else moved)
        field.update(vertices + 5.0)  # the domain moves: a new BVH build
        points = rng.uniform(-2.0, 2.0, (500, 3))
        for mode in ("adf", "exact"):
            field.query(points, mode=mode, outputs=QUERY_OUTPUTS)
            field.query(points.astype(np.float32), mode=mode, outputs=("distance", "normal"))
        field.slice("x", 0.1, resolution=(16, 24), max_level=2)
        field.stats()
    print("---- work ends ----", flush=True)
    """
)


def _loads_during_work(device: str, warm: bool) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, device, "1" if warm else "0"],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    work = done.stdout.split("---- work begins ----", 1)[1].split("---- work ends ----", 1)[0]
    return [line for line in work.splitlines() if line.startswith("Module ") and " load on device" in line]


def test_after_warm_up_the_work_loads_no_module(device):
    loads = _loads_during_work(device, warm=True)
    assert loads == [], json.dumps(loads, indent=1)


@pytest.mark.parametrize("device", ["cpu"])
def test_without_warm_up_the_same_work_loads_modules(device):
    assert len(_loads_during_work(device, warm=False)) > 0
