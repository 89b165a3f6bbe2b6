"""Two or more engine revisions timed in turn, a few frames each, over many rounds, so that a machine's drift
between runs (0.1 ms of a 2.3 ms update on an H200, 2026-11-29) falls on every revision alike.

    python3 -m badf.bench.interleave --variant main=.ab/main --variant tree=. --mesh stanford-bunny --depth 7

Each variant is a folder holding the packages (server, protocol, client, cli, bench, web_viewer), as the
repository's root or a `bench/ab.sh prepare` archive does. Each runs in a process of its own, which imports
`badf` from that folder, registers the mesh and waits; the parent then hands each in turn a round of coherent
frames (`deform`, as `badf bench engine`) and collects each frame's wall time, device total and device time
after the upload stage (whose events bracket host work). At the end every variant answers the same points:
the report gives each one's error against the float64 oracle and the largest difference between variants, so
a speed-up that changed answers shows. With `--queries R`, each round also times R ADF queries of two batches
per variant (wall clock, synchronised): `near`, 65,536 points within about a finest cell of the rest surface, and
`box`, 65,536 uniform in the bounding box grown by a tenth; the report adds how many answers of each batch equal
exact mode's to the bit (the points the ADF kernel answers exactly). Prints a table; `--out` writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

import numpy as np

from badf.bench._common import deform, find_mesh, timestamp

_PACKAGES = ("protocol", "client", "server", "web_viewer", "cli", "bench")

# What each variant's process runs: commands on stdin, one JSON line of results for each on stdout.
_WORKER = r"""
import json, os, sys, time
import numpy as np
from badf.bench._common import deform, start_warp
mesh, depth, device = sys.argv[1], int(sys.argv[2]), sys.argv[3]
import warp as wp
device = start_warp(device)
from badf.server.adf import DistanceField
import badf.server.adf as adf
data = np.load(mesh)
vertices, faces = data["vertices"], data["faces"]
field = DistanceField(vertices, faces, depth=depth, device=device)
k = 0
def answer(reply):
    sys.stdout.write(json.dumps(reply) + "\n"); sys.stdout.flush()
answer({"ready": True, "engine": os.path.realpath(adf.__file__)})
for line in sys.stdin:
    command = line.split()
    if command[0] == "run":
        walls, totals, after = [], [], []
        for _ in range(int(command[1])):
            k += 1
            frame = deform(vertices, 0.02 * k)
            wp.synchronize_device(device)
            start = time.perf_counter()
            field.update(frame)
            wp.synchronize_device(device)
            walls.append((time.perf_counter() - start) * 1e3)
            stages = field.stats()["times_ms"]
            totals.append(stages["total"])
            after.append(stages["total"] - stages.get("upload", 0.0))
        answer({"wall": walls, "total": totals, "after_upload": after})
    elif command[0] == "queries":
        batches, repeats, reply = np.load(command[1]), int(command[2]), {}
        for name in batches.files:
            points = batches[name]
            field.query(points, mode="adf")
            walls = []
            for _ in range(repeats):
                wp.synchronize_device(device)
                start = time.perf_counter()
                field.query(points, mode="adf")
                wp.synchronize_device(device)
                walls.append((time.perf_counter() - start) * 1e3)
            reply[name] = walls
        answer(reply)
    elif command[0] == "exactly":
        batches = np.load(command[1])
        answer({name: int(np.count_nonzero(field.query(batches[name], mode="adf").distance
                                           == field.query(batches[name], mode="exact").distance))
                for name in batches.files})
    elif command[0] == "answer":
        points = np.load(command[1])
        stats = field.stats()
        answer({"adf": field.query(points, mode="adf").distance.tolist(),
                "exact": field.query(points, mode="exact").distance.tolist(),
                "frame": field.frame, "captures": stats["graph_captures"], "replans": stats["replans"],
                "memory_bytes": sum(stats["memory_bytes"].values()), "frames_run": k})
    else:
        break
"""


def _package_root(folder: pathlib.Path, scratch: pathlib.Path, name: str) -> pathlib.Path:
    """A folder holding `badf/` whose packages are `folder`'s, for the variant's PYTHONPATH."""
    missing = [p for p in _PACKAGES if not (folder / p).is_dir()]
    if missing:
        raise SystemExit(f"interleave: {folder} has no {', '.join(missing)} (a repository root or .ab/NAME)")
    root = scratch / name / "badf"
    root.mkdir(parents=True)
    for package in _PACKAGES:
        (root / package).symlink_to((folder / package).resolve())
    return root.parent


def variant_environment(root: pathlib.Path) -> dict[str, str]:
    """This process's environment with `root` (_package_root) first on PYTHONPATH, so `badf` imports from it."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), *filter(None, [os.environ.get("PYTHONPATH")])]))


class _Variant:
    def __init__(self, name: str, root: pathlib.Path, mesh: pathlib.Path, depth: int, device: str):
        """A process importing `badf` from `root` (_package_root), with the mesh registered."""
        self.name = name
        env = variant_environment(root)
        self.process = subprocess.Popen([sys.executable, "-c", _WORKER, str(mesh), str(depth), device], env=env,
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.engine = self._reply()["engine"]
        self.wall: list[float] = []
        self.total: list[float] = []
        self.after_upload: list[float] = []

    def _reply(self) -> dict:
        line = self.process.stdout.readline()
        if not line:
            raise SystemExit(f"interleave: variant {self.name}'s process ended (exit {self.process.wait()})")
        return json.loads(line)

    def ask(self, command: str) -> dict:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()
        return self._reply()

    def run(self, frames: int) -> dict:
        reply = self.ask(f"run {frames}")
        self.wall += reply["wall"]
        self.total += reply["total"]
        self.after_upload += reply["after_upload"]
        return reply

    def close(self) -> None:
        if self.process.poll() is None:
            try:
                self.process.stdin.write("quit\n")
                self.process.stdin.close()
                self.process.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self.process.kill()
                self.process.wait()


def query_batches(vertices: np.ndarray, faces: np.ndarray, depth: int, count: int = 65_536) -> dict[str, np.ndarray]:
    """The batches `--queries` times: `near`, within about a finest cell (the box's longest side / 2^depth) of the
    surface, and `box`, uniform in the bounding box grown by a tenth; float32, from a fixed seed."""
    from badf.bench._cases import near_surface, surface_samples

    rng = np.random.default_rng(1)
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    cell = float((hi - lo).max()) / 2**depth
    near = near_surface(surface_samples(vertices, faces, count, rng), cell, rng)
    box = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (count, 3))
    return {"near": near.astype(np.float32), "box": box.astype(np.float32)}


def measure(variants: dict[str, pathlib.Path], mesh: pathlib.Path, *, depth: int, device: str, rounds: int,
            frames: int, warm_up: int, points: int, queries: int = 0) -> dict:
    """Each variant's frames (and with `queries`, that many ADF queries of each of `query_batches`), round by
    round in turn (the first of each round's order alternating), then the same points answered by each."""
    from badf.bench._oracle import bbox_diagonal, signed_distance

    with tempfile.TemporaryDirectory() as scratch:
        roots = {name: _package_root(folder, pathlib.Path(scratch), name) for name, folder in variants.items()}
        running: list[_Variant] = []
        data = np.load(mesh)
        vertices = data["vertices"]
        batches = pathlib.Path(scratch) / "batches.npz"
        if queries:
            np.savez(batches, **query_batches(vertices, data["faces"], depth))
        query_rounds = {v: {} for v in variants}
        try:
            for name, root in roots.items():
                running.append(_Variant(name, root, mesh, depth, device))
            for variant in running:
                variant.ask(f"run {warm_up}")  # to the first replayed frames: captures and first plans
            per_round = {v.name: {"wall": [], "after_upload": []} for v in running}
            for r in range(rounds):
                for variant in running if r % 2 == 0 else running[::-1]:
                    times = variant.run(frames)
                    for kind in ("wall", "after_upload"):
                        per_round[variant.name][kind].append(float(np.median(times[kind])))
                    if queries:
                        for batch, walls in variant.ask(f"queries {batches} {queries}").items():
                            query_rounds[variant.name].setdefault(batch, []).append(
                                {"median": float(np.median(walls)), "min": float(np.min(walls))})
            exactly = {v.name: v.ask(f"exactly {batches}") for v in running} if queries else {}
            lo, hi = vertices.min(axis=0), vertices.max(axis=0)
            probe = np.random.default_rng(0).uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (points, 3))
            path = pathlib.Path(scratch) / "points.npy"
            np.save(path, probe.astype(np.float32))
            answers = {v.name: v.ask(f"answer {path}") for v in running}
        finally:
            for variant in running:
                variant.close()
    # every variant ran as many frames, so each holds the same last frame, which the oracle works out again
    frames_run = {a["frames_run"] for a in answers.values()}
    if len(frames_run) != 1:
        raise RuntimeError(f"interleave: the variants ran different frame counts {sorted(frames_run)}")
    frame_vertices = deform(vertices, 0.02 * frames_run.pop()).astype(np.float64)
    truth = signed_distance(probe.astype(np.float32).astype(np.float64), frame_vertices, data["faces"])
    diagonal = bbox_diagonal(frame_vertices)
    first = next(iter(answers))
    report = {"benchmark": "interleave", "date": timestamp(), "mesh": str(mesh), "depth": depth, "device": device,
              "rounds": rounds, "frames_per_round": frames, "variants": {}}
    for variant in running:
        a = answers[variant.name]
        report["variants"][variant.name] = {
            "engine": variant.engine,
            "wall_ms": _summary(variant.wall), "device_total_ms": _summary(variant.total),
            "after_upload_ms": _summary(variant.after_upload),
            # its round medians less the first variant's, round by round: drift cancels within a round
            "wall_vs_first_ms": _vs_first(per_round, variant.name, first, "wall"),
            "after_upload_vs_first_ms": _vs_first(per_round, variant.name, first, "after_upload"),
            "graph_captures": a["captures"], "replans": a["replans"], "memory_bytes": a["memory_bytes"],
            "adf_max_error_diag": float(np.max(np.abs(np.asarray(a["adf"]) - truth)) / diagonal),
            "exact_max_error_diag": float(np.max(np.abs(np.asarray(a["exact"]) - truth)) / diagonal),
            "adf_max_difference_from_first_diag": float(
                np.max(np.abs(np.asarray(a["adf"]) - np.asarray(answers[first]["adf"]))) / diagonal),
        }
        if queries:
            report["variants"][variant.name]["queries"] = {
                batch: {"median_ms": round(float(np.median([r["median"] for r in per])), 4),
                        "min_ms": round(float(np.min([r["min"] for r in per])), 4),
                        # its round medians less the first variant's, round by round
                        "vs_first_ms": round(float(np.median(np.subtract(
                            [r["median"] for r in per], [r["median"] for r in query_rounds[first][batch]]))), 4),
                        "answered_exactly": exactly[variant.name][batch]}
                for batch, per in query_rounds[variant.name].items()}
    report["queries_per_round"] = queries
    return report


def _vs_first(per_round: dict, name: str, first: str, measure: str) -> float:
    """The median over rounds of `name`'s round median of `measure` less the first variant's in the same round."""
    return round(float(np.median(np.subtract(per_round[name][measure], per_round[first][measure]))), 4)


def _summary(values: list[float]) -> dict:
    return {"median": round(float(np.median(values)), 4), "p10": round(float(np.percentile(values, 10)), 4),
            "p90": round(float(np.percentile(values, 90)), 4), "frames": len(values)}


def _print(report: dict) -> None:
    print(f"interleave: {report['mesh']} at depth {report['depth']} on {report['device']}, {report['rounds']} rounds "
          f"of {report['frames_per_round']} frames, {report['date']}")
    print(f"{'variant':<10} {'wall':>7} {'vs first':>9} {'total':>7} {'after up.':>9} {'vs first':>9} {'adf err':>9} "
          f"{'exact err':>9} {'adf diff':>9} {'MiB':>7}")
    for name, v in report["variants"].items():
        print(f"{name:<10} {v['wall_ms']['median']:>7.3f} {v['wall_vs_first_ms']:>+9.4f} {v['device_total_ms']['median']:>7.3f} "
              f"{v['after_upload_ms']['median']:>9.4f} {v['after_upload_vs_first_ms']:>+9.4f} "
              f"{v['adf_max_error_diag']:>9.2e} {v['exact_max_error_diag']:>9.2e} "
              f"{v['adf_max_difference_from_first_diag']:>9.2e} {v['memory_bytes'] / 2**20:>7.2f}")
    print("ms, medians over every frame; each 'vs first' is the median over rounds of each round's difference; errors "
          "against the float64 oracle, in bounding-box diagonals, at the last frame")
    if report["queries_per_round"]:
        print(f"ADF queries of 65,536 points, {report['queries_per_round']} a round; wall ms (synchronised):")
        print(f"{'variant':<10} {'batch':<6} {'median':>8} {'min':>8} {'vs first':>9} {'exactly':>8}")
        for name, v in report["variants"].items():
            for batch, q in v["queries"].items():
                print(f"{name:<10} {batch:<6} {q['median_ms']:>8.3f} {q['min_ms']:>8.3f} {q['vs_first_ms']:>+9.4f} "
                      f"{q['answered_exactly']:>8}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m badf.bench.interleave", description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", action="append", required=True, metavar="NAME=FOLDER",
                        help="a revision's packages (repeat, two or more)")
    parser.add_argument("--mesh", required=True, help="a .npz file, or a shared mesh's name")
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--device", default=None, help="default: the first GPU, else the CPU")
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--frames", type=int, default=10, help="frames a variant runs in each round")
    parser.add_argument("--warm-up", type=int, default=10)
    parser.add_argument("--points", type=int, default=1000, help="points answered at the end, against the oracle")
    parser.add_argument("--queries", type=int, default=0,
                        help="ADF queries of each of two 65,536-point batches a variant times in each round (0: none)")
    parser.add_argument("--out", type=pathlib.Path)
    args = parser.parse_args(argv)
    variants = {}
    for given in args.variant:
        name, sep, folder = given.partition("=")
        if not sep or not name or name in variants:
            parser.error(f"--variant {given!r}: give NAME=FOLDER, each NAME once")
        variants[name] = pathlib.Path(folder)
    if len(variants) < 2:
        parser.error("give two or more --variant")
    for name, count in (("--rounds", args.rounds), ("--frames", args.frames), ("--points", args.points)):
        if count < 1:
            parser.error(f"{name} must be at least 1, got {count}")
    if args.queries < 0:
        parser.error(f"--queries must be 0 or more, got {args.queries}")
    device = args.device if args.device is not None else ("cuda:0" if _has_cuda() else "cpu")
    report = measure(variants, find_mesh(args.mesh), depth=args.depth, device=device, rounds=args.rounds,
                     frames=args.frames, warm_up=max(args.warm_up, 0), points=args.points,
                     queries=args.queries)
    _print(report)
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    return 0


def _has_cuda() -> bool:
    import warp as wp

    wp.config.log_level = wp.LOG_ERROR
    return wp.get_cuda_device_count() > 0


if __name__ == "__main__":
    sys.exit(main())
