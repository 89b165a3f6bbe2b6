"""Scale-out benchmark: aggregate throughput of several client processes against one worker, then against
N workers (one per GPU), all behind one Zenoh router.

    python -m badf.bench.scaleout --mesh PATH.npz [--device cuda|cpu] [--workers N] [--clients 8,16]
                                  [--points 65536] [--seconds 15] [--depth 7] [--small] [--out results.json]

For each worker count (1, then N) it starts what `badf serve --gpus` runs (a router process and the worker
processes behind it, on cuda:0..N-1, or all on the CPU), registers one copy of the mesh per client through
the client's least-loaded placement, and for each client count starts that many client processes (spawn).
Each client, after a warm-up, loops for `--seconds`: stream the next frame of a deforming copy of the mesh,
then query `--points` points of the field (distance, adf): one round trip carries one frame and one query.
(The worker usually applies the frame before it answers the query; when the query overtakes the frame,
the reply names the older frame and the next frame may replace this one unapplied: counted as
`stale_replies` and as frames dropped.) Reported, per worker and client count:
aggregate frames applied per second and query points answered per second (sums over the clients of what
each did in its own timed window), the round trip's median and p99, frames dropped, and the speed-up over
one worker with the same clients. The workers' own counters are reported beside the clients' as a check.
With N GPUs it also runs N workers all on cuda:0, a control: what N worker processes gain on one GPU
(more CPU for Python and Zenoh) is not the second GPU's doing.

On the CPU back-end the workers share this machine's cores, so N CPU workers do not show scaling: run it
on a machine with N GPUs for that; CPU runs only check that the benchmark works.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import time
from typing import Any

import numpy as np

from badf.bench._common import BenchFlagError, deform, fill_sized_defaults, print_table, timestamp
from badf.server._mesh_files import MESH_HELP, read_mesh

_SPAWN = multiprocessing.get_context("spawn")
_FRAME_COUNT = 16
_FULL = {"clients": "8,16", "points": 65_536, "seconds": 15.0, "depth": 7, "warmup": 10}
_SMALL = {"clients": "2,4", "points": 4096, "seconds": 4.0, "depth": 5, "warmup": 3}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mesh", required=True, help=MESH_HELP)
    parser.add_argument(
        "--device", choices=("cuda", "cpu"), default=None, help="cuda: workers on cuda:0..N-1; cpu: N CPU workers "
        "(default: cuda when a CUDA device is visible)",
    )  # fmt: skip
    parser.add_argument("--workers", type=int, help="N (default: every visible GPU; on the CPU: 2)")
    parser.add_argument("--small", action="store_true", help="CPU-sized defaults for the flags below")
    parser.add_argument("--clients", help="client process counts, comma-separated (8,16; small: 2,4)")
    parser.add_argument("--points", type=int, help="points per query (65,536; small: 4,096)")
    parser.add_argument("--seconds", type=float, help="timed seconds per run (15; small: 4)")
    parser.add_argument("--depth", type=int, help="octree depth (7; small: 5)")
    parser.add_argument("--warmup", type=int, help="untimed frame + query round trips per client first (10; small: 3)")
    parser.add_argument("--out", default=None, help="write the full results as JSON here")


def run(args: argparse.Namespace) -> int:
    from badf.server._cuda import NoCudaDeviceError, visible_cuda_device_count

    fill_sized_defaults(args, _SMALL, _FULL)
    try:
        gpu_count = visible_cuda_device_count()
    except NoCudaDeviceError as error:
        gpu_count, no_gpu = 0, str(error)
    device = args.device if args.device is not None else ("cuda" if gpu_count else "cpu")
    if device == "cuda" and not gpu_count:
        raise BenchFlagError(f"--device cuda: {no_gpu}")
    workers = args.workers or (gpu_count if device == "cuda" else 2)
    # one worker per GPU, or per CPU core: 100 CPU workers on 2 cores took 20 GB and measured only contention
    most = gpu_count if device == "cuda" else (os.cpu_count() or 1)
    if not 1 <= workers <= most:
        raise BenchFlagError(f"--workers must be 1 to {most} (one per {'GPU' if device == 'cuda' else 'CPU core'} "
                             f"here), got {workers}")
    client_counts = sorted({int(count) for count in args.clients.split(",") if count})
    if not client_counts or client_counts[0] < 1 or args.points < 1 or args.seconds <= 0:
        raise BenchFlagError("--clients, --points and --seconds must be positive")

    vertices, faces = read_mesh(args.mesh)
    devices = [f"cuda:{index}" for index in range(workers)] if device == "cuda" else ["cpu"] * workers
    report: dict[str, Any] = {
        "benchmark": "scaleout",
        "date": timestamp(),
        "host": platform.node(),
        "cpu_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "device_names": _device_names(device, workers),
        "mesh": {"path": args.mesh, "vertices": len(vertices), "faces": len(faces)},
        "depth": args.depth,
        "points_per_query": args.points,
        "seconds": args.seconds,
        "warmup_round_trips": args.warmup,
        "runs": [],
    }
    layouts = [devices[:1]] + ([devices] if workers > 1 else [])
    if device == "cuda" and workers > 1:
        layouts.append(["cuda:0"] * workers)  # the control: as many worker processes, one GPU
    for layout in layouts:
        report["runs"] += _phase(args, layout, client_counts)
    _add_speedups(report["runs"])
    _print(report, device)
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(report, handle, indent=2)
        print("wrote", args.out)
    return 0


def _phase(args: argparse.Namespace, devices: list[str], client_counts: list[int]) -> list[dict[str, Any]]:
    """A router and a worker per device; one object per client, placed by the client; one run per count."""
    from badf.client import Client
    from badf.server import RouterSettings, WorkerSettings, workers_process
    from badf.server._run import free_loopback_endpoint

    endpoint = free_loopback_endpoint()
    router = RouterSettings(namespace="bench", listen=(endpoint,))
    workers = [
        WorkerSettings(worker_id=f"w{index}", namespace="bench", device=device, stats_interval_s=3600.0)
        for index, device in enumerate(devices)
    ]
    vertices, faces = read_mesh(args.mesh)
    print(f"\n{len(devices)} worker(s) on {', '.join(devices)}: starting", flush=True)
    with workers_process(router, workers, start_timeout_s=900.0), Client(endpoint, namespace="bench", timeout=300) as client:
        _wait_for(lambda: len(client.workers()) == len(workers), 120.0, "the workers to answer through the router")
        names = [f"object{index}" for index in range(max(client_counts))]
        for name in names:  # least-loaded placement: the objects alternate over the workers
            client.register(name, vertices, faces, depth=args.depth)
        placement = {info.worker: info.object_count for info in client.workers()}
        print(f"placement of {len(names)} objects: {placement}", flush=True)
        runs = []
        for count in client_counts:
            run = _timed_run(args, endpoint, client, names[:count])
            run.update(workers=len(devices), devices=devices, placement=placement)
            runs.append(run)
            print(
                f"  {count} clients: {run['frames_per_s']:.1f} frames/s, {run['points_per_s'] / 1e6:.2f} Mpoints/s, "
                f"round trip median {run['median_ms']:.2f} ms",
                flush=True,
            )
        accuracy = _served_accuracy(client, names[: len(devices)], vertices, faces)
        print(f"  the answers' accuracy: {accuracy['points']} points on {accuracy['objects']} object(s) against the "
              f"float64 oracle: {accuracy['max_error_diag']:.2e} / {accuracy['mean_error_diag']:.2e} diagonals "
              f"(max / mean)", flush=True)
    for run in runs:
        run["accuracy"] = accuracy
    return runs


def _served_accuracy(client, names: list[str], vertices: np.ndarray, faces: np.ndarray) -> dict[str, Any]:
    """What the timed queries' answers are worth: the objects `names` (one per worker, as placement alternates),
    set to the mesh's own frame, answer a sample of points like the clients' against the float64 oracle."""
    from badf.bench._oracle import ORACLE_SAMPLE, errors_against, signed_distance

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    points = np.random.default_rng(0).uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), size=(ORACLE_SAMPLE, 3))
    points = points.astype(np.float32)
    answers = []
    for name in names:
        remote = client.object(name)
        remote.update(vertices)
        answers.append(remote.query(points).distance)
    return {"objects": len(names), **errors_against(np.stack(answers), signed_distance(points, vertices, faces), vertices)}


def _timed_run(args: argparse.Namespace, endpoint: str, client, names: list[str]) -> dict[str, Any]:
    """`len(names)` client processes, one object each, timed together; their sums and the workers' counters."""
    barrier = _SPAWN.Barrier(len(names) + 1)
    results = _SPAWN.Queue()
    processes = [
        _SPAWN.Process(
            target=_client_main,
            args=(endpoint, name, args.mesh, args.points, args.seconds, args.warmup, index, barrier, results),
            name=f"badf-bench-client-{index}",
            daemon=True,
        )
        for index, name in enumerate(names)
    ]
    for process in processes:
        process.start()
    try:
        barrier.wait(timeout=600)  # every client has warmed up; all start their timed loop now
        before = {info.worker: info for info in client.workers()}
        clients = [results.get(timeout=args.seconds + 600) for _ in processes]
        after = {info.worker: info for info in client.workers()}
    except BaseException:  # Ctrl-C, SIGTERM or a failure: the clients need not finish their timed window
        for process in processes:
            process.terminate()
        raise
    finally:
        for process in processes:
            process.join(60)
            if process.is_alive():
                process.kill()
    failed = [result["error"] for result in clients if "error" in result]
    if failed:
        raise SystemExit(f"badf bench scaleout: a client failed: {failed[0]}")
    latencies = np.concatenate([np.asarray(result.pop("latencies_s")) for result in clients])
    return {
        "clients": len(names),
        "frames_per_s": sum(result["frames_applied"] / result["seconds"] for result in clients),
        "points_per_s": sum(result["points"] / result["seconds"] for result in clients),
        "round_trips": int(latencies.size),
        "median_ms": float(np.median(latencies) * 1e3),
        "p99_ms": float(np.percentile(latencies, 99) * 1e3),
        "frames_dropped": sum(result["frames_dropped"] for result in clients),
        "stale_replies": sum(result["stale_replies"] for result in clients),
        "per_client": clients,
        "per_worker": {
            worker: {
                "frames_applied": after[worker].frames_applied - before[worker].frames_applied,
                "points_answered": after[worker].points_answered - before[worker].points_answered,
            }
            for worker in after
        },
    }


def _client_main(
    endpoint: str, name: str, mesh: str, points: int, seconds: float, warmup: int, index: int, barrier, results
) -> None:
    """One client process: warm up, wait for the others, then stream + query round trips for `seconds`."""
    from badf.client import Client

    try:
        vertices, _ = read_mesh(mesh)
        frames = [deform(vertices, (index + step / _FRAME_COUNT) % 1.0) for step in range(_FRAME_COUNT)]
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        rng = np.random.default_rng(index)
        cloud = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), size=(points, 3)).astype(np.float32)
        with Client(endpoint, namespace="bench", timeout=300) as client:
            obj = client.object(name)
            for step in range(warmup):
                obj.stream(frames[step % _FRAME_COUNT])
                obj.query(cloud)
            before = obj.info()
            barrier.wait(timeout=600)
            latencies = []
            started = time.perf_counter()
            deadline = started + seconds
            step = stale = 0
            while True:
                begin = time.perf_counter()
                sent = obj.stream(frames[step % _FRAME_COUNT])
                stale += obj.query(cloud).frame < sent
                end = time.perf_counter()
                latencies.append(end - begin)
                step += 1
                if end >= deadline:
                    break
            elapsed = end - started
            after = obj.info()
        results.put(
            {
                "object": name,
                "worker": obj.worker,
                "seconds": elapsed,
                "round_trips": step,
                "frames_applied": after.frames_applied - before.frames_applied,
                "frames_dropped": after.frames_dropped - before.frames_dropped,
                "stale_replies": stale,
                "points": step * points,
                "latencies_s": latencies,
            }
        )
    except Exception as error:  # noqa: BLE001 - reported to the parent, which stops the benchmark
        results.put({"error": f"{name}: {type(error).__name__}: {error}"})
        barrier.abort()


def _add_speedups(runs: list[dict[str, Any]]) -> None:
    """Each run's throughput over the one-worker run with the same number of clients."""
    single = {run["clients"]: run for run in runs if run["workers"] == 1}  # the first phase
    for run in runs:
        base = single[run["clients"]]
        run["frames_speedup"] = run["frames_per_s"] / base["frames_per_s"] if base["frames_per_s"] else 0.0
        run["points_speedup"] = run["points_per_s"] / base["points_per_s"] if base["points_per_s"] else 0.0


def _print(report: dict[str, Any], device: str) -> None:
    mesh = report["mesh"]
    print_table(
        f"scale-out on {', '.join(report['device_names'])}; {mesh['path']} ({mesh['faces']} triangles), depth "
        f"{report['depth']}; each client: stream a frame + query {report['points_per_query']} points, "
        f"{report['seconds']:g} s",
        ["workers", "devices", "clients", "frames/s", "Mpoints/s", "median ms", "p99 ms", "dropped", "x frames",
         "x points"],
        [
            [run["workers"], ",".join(sorted(set(run["devices"]))), run["clients"], round(run["frames_per_s"], 1),
             round(run["points_per_s"] / 1e6, 3),
             round(run["median_ms"], 2), round(run["p99_ms"], 2), run["frames_dropped"],
             round(run["frames_speedup"], 2), round(run["points_speedup"], 2)]
            for run in report["runs"]
        ],
    )  # fmt: skip
    if device == "cpu":
        print(f"(CPU workers share this machine's {report['cpu_cores']} cores: these numbers are not scaling evidence)")


def _device_names(device: str, count: int) -> list[str]:
    if device == "cpu":
        return [f"CPU back-end ({platform.processor() or platform.machine()})"]
    from badf.server._cuda import cuda_device_names

    return [f"{name} (cuda:{index})" for index, name in enumerate(cuda_device_names()[:count])]


def _wait_for(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit(f"badf bench scaleout: timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(0.1)


def main() -> int:
    from badf.bench._cli import main_of

    return main_of("scaleout")


if __name__ == "__main__":
    raise SystemExit(main())
