"""Probe, not part of the product (python3 bench/probes/probe_quantised_boxes.py MESH.npz [device] [--bits 8 ...]
[--out FILE]): what quantising the 4-wide view's boxes would cost the corner searches in node visits, before building
it. A compressed wide BVH stores each child's box in a few bits a plane against its node's own box, rounded outward;
engine.md's memory floor counts on 8 bits to bring the bunny's boxes from 4.44 to about 2.2 MB.

The probe takes the engine's own view after a coherent update, replaces every child's box by the box its quantised
planes would decode to (each lower plane rounded down, each upper one up, on a grid of 2^bits - 1 steps across the
node's box), and runs the engine's unchanged search kernel over the same corners with visit budgets: how many
searches outrun each budget says how the walks lengthened. The answers must stay the engine's: a box that only grew
is still a lower bound, so every search still ends on the same leaf at the same distance. The device time (or, on
the CPU back-end, the wall time of one thread, which tracks the total work) is printed too, but on a GPU the real
price is in the decoding, which this probe does not run."""
import argparse
import json
import sys

import numpy as np
import warp as wp

from badf.server.adf import _distance as D

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _capture import captured_search, device_times  # noqa: E402

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("mesh")
parser.add_argument("device", nargs="?", default="cuda:0")
parser.add_argument("--bits", type=int, nargs="+", default=[4, 6, 8, 10, 16])
parser.add_argument("--budgets", type=int, nargs="+", default=[16, 32, 64, 128, 256])
parser.add_argument("--out")
args = parser.parse_args()

field, inputs, count, truth = captured_search(args.mesh, args.device)
capacity = inputs[2]
planes = field._bvh.wide.planes
original = planes.numpy().copy()  # (6 k + axis plane) rows of 4 entries: lower x, y, z, then upper x, y, z


def quantised(rows: np.ndarray, bits: int) -> np.ndarray:
    """Each child's box as its planes, quantised outward to `bits` against its node's own box, would decode."""
    boxes = rows.reshape(-1, 6, 4).astype(np.float64)  # node, plane, entry
    lower, upper = boxes[:, :3, :], boxes[:, 3:, :]
    used = lower <= upper  # empty entries hold an inverted box, left as they are
    node_lo = np.where(used, lower, np.inf).min(axis=2, keepdims=True)
    node_hi = np.where(used, upper, -np.inf).max(axis=2, keepdims=True)
    live = np.isfinite(node_lo) & np.isfinite(node_hi)
    node_lo, node_hi = np.where(live, node_lo, 0.0), np.where(live, node_hi, 1.0)
    steps = float((1 << bits) - 1)
    step = np.maximum(node_hi - node_lo, 1e-30) / steps
    q_lo = np.clip(np.floor((lower - node_lo) / step), 0, steps)
    q_hi = np.clip(np.ceil((upper - node_lo) / step), 0, steps)
    out_lo = (node_lo + q_lo * step).astype(np.float32)
    out_hi = (node_lo + q_hi * step).astype(np.float32)
    # decoding rounds to float32: keep it outward of the box it stands for
    out_lo = np.where(out_lo > lower, np.nextafter(out_lo, np.float32(-np.inf)), out_lo)
    out_hi = np.where(out_hi < upper, np.nextafter(out_hi, np.float32(np.inf)), out_hi)
    out = boxes.copy()
    out[:, :3, :] = np.where(used, out_lo, lower)
    out[:, 3:, :] = np.where(used, out_hi, upper)
    assert np.all(out[:, :3, :][used] <= lower[used]) and np.all(out[:, 3:, :][used] >= upper[used])
    return out.astype(np.float32).reshape(rows.shape)


distance = wp.zeros(capacity, dtype=float, device=args.device)
nearest = wp.zeros(capacity, dtype=int, device=args.device)
long_count = wp.zeros(1, dtype=int, device=args.device)
long_corner = wp.zeros(capacity, dtype=int, device=args.device)
long_start = wp.zeros(capacity, dtype=wp.int64, device=args.device)
long_best = wp.zeros(capacity, dtype=wp.int64, device=args.device)
unseeded = wp.zeros(1, dtype=int, device=args.device)


def search(budget: int) -> None:
    long_count.zero_()
    wp.launch(D.corner_searches_budgeted, dim=capacity, inputs=list(inputs) + [budget, 0, unseeded, unseeded],
              outputs=[distance, nearest, long_count, long_corner, long_start, long_best], device=args.device,
              block_dim=D.SEARCH_BLOCK_DIM)


rows = []
for bits in [0] + args.bits:  # 0: the engine's float32 boxes
    planes.assign(original if bits == 0 else quantised(original, bits))
    outrun = {}
    for budget in args.budgets:
        search(budget)
        outrun[budget] = int(long_count.numpy()[0])
    search(D.UNLIMITED_VISITS)
    got_leaf = nearest.numpy()[:count]
    got = distance.numpy()[:count]
    if bits == 0:
        engine_leaf = got_leaf.copy()
    repeats = 3 if args.device == "cpu" else 20
    ms = device_times(lambda: search(D.UNLIMITED_VISITS), args.device, repeats)[0]
    rows.append(dict(bits=bits or "float32", outrun=outrun,
                     search_ms=round(ms, 4), differ_from_engine=int(np.count_nonzero(got != truth)),
                     leaves_differ=int(np.count_nonzero(got_leaf != engine_leaf))))
    print(rows[-1], flush=True)
planes.assign(original)
print(f"\n{args.mesh} depth 7, {count} corners, {wp.get_device(args.device).name}: searches outrunning a budget of "
      "binary node visits (a 4-wide visit counts two)")
print(f"{'boxes':<10}" + "".join(f"{'>' + str(b):>9}" for b in args.budgets) + f"{'search ms':>11}{'differ':>8}")
for r in rows:
    print(f"{str(r['bits']) + (' bits' if r['bits'] != 'float32' else ''):<10}"
          + "".join(f"{r['outrun'][b]:>9}" for b in args.budgets)
          + f"{r['search_ms']:>11.3f}{r['differ_from_engine'] + r['leaves_differ']:>8}")
if args.out:
    with open(args.out, "w") as f:
        json.dump(dict(mesh=args.mesh, device=wp.get_device(args.device).name, corners=count, rows=rows), f, indent=1)
