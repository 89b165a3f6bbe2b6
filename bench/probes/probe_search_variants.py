"""Probe, not part of the product (python3 bench/probes/probe_search_variants.py MESH.npz [device] [--out FILE]): the
engine's corner-search kernel against variants of it over the same corners and seeds, alternated round by round.

probe_slabs found its own copy of the corner walk (counting visits, without a budget or a list of long searches)
7 to 13% faster on an H200 than the engine's kernel of 80b00b0, over three meshes. The two differed in two ways: the
engine's kernel is capped at SEARCH_MAX_REGISTERS registers per thread (chosen on an H100 on 2026-11-22, for the
binary walk before the 4-wide view), and it carried a visit budget and the listing of long searches, which only
`corner_searches_budgeted` carries since 2026-12-02 (the first run of this probe decided that). Each variant here
changes one of them; every answer is checked against the engine's, corner for corner.
"""
import json
import sys

import numpy as np
import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search, device_times, engine_search, mesh_device_out  # noqa: E402
from probe_slabs import _walk  # noqa: E402

from badf.server.adf import _distance  # noqa: E402

ROUNDS = 7


def main():
    path, device, out = mesh_device_out()
    field, inputs, count, truth = captured_search(path, device)
    capacity = inputs[2]
    truth_leaf = field._corners.leaf.numpy()[:count].copy()
    name = wp.get_device(device).name
    distance = wp.zeros(capacity, dtype=float, device=device)
    nearest = wp.zeros(capacity, dtype=int, device=device)
    visits = wp.zeros(capacity, dtype=int, device=device)
    passed = wp.zeros(capacity, dtype=int, device=device)
    no_slab = wp.zeros(1, dtype=wp.vec4, device=device)
    no_slab_hi = wp.zeros(1, dtype=wp.float32, device=device)
    engine_kernel = _distance.corner_searches

    def engine_with_cap(cap):
        kernel = wp.kernel(engine_kernel.func, enable_backward=False, module="unique",
                           module_options=_distance.EXACT_ROUNDING, cuda_max_registers=cap,
                           name=f"{engine_kernel.key}_probe_cap{cap}")

        def launch():
            _distance.corner_searches = kernel
            try:
                engine_search(inputs, capacity, distance, nearest, device)()
            finally:
                _distance.corner_searches = engine_kernel
        return launch, kernel

    def counted(cap):
        kernel = _walk(False, cap)

        def launch():
            wp.launch(kernel, dim=capacity, inputs=[*inputs, no_slab, no_slab_hi],
                      outputs=[distance, nearest, visits, passed], device=device, block_dim=_distance.SEARCH_BLOCK_DIM)
        return launch, kernel

    variants = {f"engine's kernel (cap {_distance.SEARCH_MAX_REGISTERS})": (
        engine_search(inputs, capacity, distance, nearest, device), engine_kernel)}
    for cap in (96, 255):
        variants[f"engine's kernel, cap {cap}"] = engine_with_cap(cap)
    for cap in (_distance.SEARCH_MAX_REGISTERS, 255):
        variants[f"walk without budget, cap {cap}"] = counted(cap)
    rows = {label: dict(variant=label, rounds_ms=[]) for label in variants}
    for label, (launch, kernel) in variants.items():
        distance.fill_(-1.0)
        launch()
        row = rows[label]
        row["distances_differ"] = int(np.count_nonzero(distance.numpy()[:count] != truth))
        row["leaves_differ"] = int(np.count_nonzero(nearest.numpy()[:count] != truth_leaf))
        if device != "cpu":
            props = wp.get_cuda_kernel_properties(kernel, device, block_dim=_distance.SEARCH_BLOCK_DIM)
            row["registers"], row["local_bytes"] = props["register_count"], props["local_memory_size"]
    for _ in range(ROUNDS):  # alternated, so a drifting clock shows in every variant alike
        for label, (launch, _kernel) in variants.items():
            rows[label]["rounds_ms"].append(round(device_times(launch, device, 10)[0], 4))
    print(f"\n{path}: depth 7, {count} corners, {name}; median ms of {ROUNDS} alternated rounds (each the median of 10)")
    print(f"{'variant':<40}{'median':>8}{'least':>8}{'most':>8}{'regs':>6}{'local':>7}{'differ':>8}")
    for row in rows.values():
        t = row["rounds_ms"]
        row["median_ms"] = round(float(np.median(t)), 4)
        print(f"{row['variant']:<40}{row['median_ms']:>8.3f}{min(t):>8.3f}{max(t):>8.3f}"
              f"{row.get('registers', 0):>6}{row.get('local_bytes', 0):>7}"
              f"{row['distances_differ'] + row['leaves_differ']:>8}")
    if out:
        with open(out, "w") as f:
            json.dump(dict(mesh=path, device=name, corners=count, rows=list(rows.values())), f, indent=1)


if __name__ == "__main__":
    main()
