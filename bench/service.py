"""Service benchmark: what the protocol and Zenoh add on top of the engine.

Measures, on one device:
  * the round trip "apply a frame of a deforming mesh, then answer a query of P points" (P = 65,536 by
    default): median and p99 latency and frames per second, through the service (a worker in its own
    process, reached over loopback) beside the same calls on the engine in this process;
  * query latency and throughput for batches of 1K to 1M points, service beside in-process;
  * the floor under both: Zenoh alone moving the same request and reply sizes (an echo router process),
    and the time the protocol's encode/decode takes for the same messages.

Runs on the CPU here with `--small`, and on a GPU with `--device cuda:0`. Writes `service.json` (every
sample's summary) and `service.md` (the tables) under `--out`, and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import platform
import socket
import struct
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

_SPAWN = multiprocessing.get_context("spawn")
_DEFAULT_MESHES = (Path("../shared/data/stanford-bunny.npz"), Path(".gpudata/stanford-bunny.npz"))
_SMALL_MESHES = (Path("tests/data/spot.npz"), Path("../shared/data/spot.npz"))
_ECHO_KEY = "bench/echo"
_FULL = {
    "depth": 7,
    "points": 65_536,
    "round_trips": 300,
    "repeats": 30,
    "batches": "1024,4096,16384,65536,262144,1048576",
}
_SMALL = {"depth": 5, "points": 4096, "round_trips": 20, "repeats": 5, "batches": "1024,4096,16384"}


@dataclass
class Timing:
    name: str
    samples: int
    median_ms: float
    p99_ms: float
    per_second: float  # round trips (or queries) per second over the whole run
    points_per_second: float = 0.0
    request_bytes: int = 0
    reply_bytes: int = 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--device", default=None, help="Warp device for the worker and the in-process engine (default: Warp's)"
    )
    parser.add_argument(
        "--mesh",
        type=Path,
        default=None,
        help="an .npz with vertices and faces (default: the Stanford bunny from ../shared/data)",
    )
    parser.add_argument("--depth", type=int, help="octree depth (default 7; 5 with --small)")
    parser.add_argument(
        "--points", type=int, help="points per query in the round trip (default 65,536; 4,096 with --small)"
    )
    parser.add_argument("--round-trips", type=int, help="timed round trips (default 300; 20 with --small)")
    parser.add_argument("--batches", help="query batch sizes, comma-separated (default 1K to 1M; to 16K with --small)")
    parser.add_argument("--repeats", type=int, help="timed queries per batch size (default 30; 5 with --small)")
    parser.add_argument(
        "--small", action="store_true",
        help="CPU-sized defaults: Spot the cow (tests/data) at depth 5, 20 round trips of 4,096 points, batches to 16K",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("bench-out"), help="folder for service.json and service.md")


def run(args: argparse.Namespace) -> int:
    defaults = _SMALL if args.small else _FULL
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    batches = [int(size) for size in args.batches.split(",") if size]
    mesh_path = _find_mesh(args.mesh, _SMALL_MESHES if args.small else _DEFAULT_MESHES)
    data = np.load(mesh_path)
    vertices = np.ascontiguousarray(data["vertices"][0] if data["vertices"].ndim == 3 else data["vertices"], np.float32)
    faces = np.ascontiguousarray(data["faces"], np.int32)
    frames = _deforming_frames(vertices, 32)
    rng = np.random.default_rng(0)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    all_points = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), size=(max(batches + [args.points]), 3)).astype(
        np.float32
    )
    points = all_points[: args.points]
    report: dict = {
        "mesh": str(mesh_path), "vertices": len(vertices), "faces": len(faces), "depth": args.depth,
        "round_trip_points": args.points, "host": platform.node(), "python": sys.version.split()[0],
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }  # fmt: skip
    timings: list[Timing] = []

    import warp as wp
    import zenoh

    from badf.client import Client
    from badf.protocol import zenoh_config
    from badf.server import WorkerSettings, run_worker
    from badf.server.adf import DistanceField

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    field = DistanceField(vertices, faces, depth=args.depth, device=args.device)
    report["device"] = field.device
    endpoint, echo_endpoint = _free_endpoint(), _free_endpoint()
    ready, echo_ready = _SPAWN.Event(), _SPAWN.Event()
    settings = WorkerSettings(worker_id="bench", listen=(endpoint,), device=args.device, stats_interval_s=3600.0)
    worker = _SPAWN.Process(target=run_worker, args=(settings, ready), daemon=True)
    echo = _SPAWN.Process(target=_echo_router, args=(echo_endpoint, echo_ready), daemon=True)
    worker.start()
    echo.start()
    try:
        _wait(ready, worker, "worker")
        _wait(echo_ready, echo, "echo router")
        echo_config = zenoh_config(mode="client", connect=[echo_endpoint], connect_timeout_s=120)
        with Client(endpoint, timeout=120) as client, zenoh.open(echo_config) as echo_session:
            remote = client.register("bench", vertices, faces, depth=args.depth)
            frame_bytes = _frame_size(frames[0])
            query_bytes, reply_bytes = _query_sizes(points)
            wire = (frame_bytes + query_bytes, reply_bytes)

            def local_round(i: int) -> None:
                field.update(frames[i % len(frames)])
                field.query(points, outputs=("distance",))

            def served_round(i: int) -> None:
                remote.update(frames[i % len(frames)])
                remote.query(points, outputs=("distance",))

            def echo_round(_i: int) -> None:
                _echo(echo_session, frame_bytes, 64)
                _echo(echo_session, query_bytes, reply_bytes)

            n = args.round_trips
            timings += [
                _time("round trip, in-process engine", local_round, n, per_item=args.points),
                _time("round trip, service", served_round, n, per_item=args.points, sizes=wire),
                _time("round trip, Zenoh echo of the same bytes", echo_round, n, sizes=wire),
                _time("update only, in-process", lambda i: field.update(frames[i % len(frames)]), n),
                _time("update only, service", lambda i: remote.update(frames[i % len(frames)]), n),
            ]
            report["engine_stats_after_update"] = field.stats()
            for size in batches:
                timings += _batch_timings(field, remote, echo_session, all_points[:size], args.repeats)
            remote.delete()
    finally:
        for process in (worker, echo):
            if process.is_alive():
                process.terminate()
                process.join(30)
            if process.is_alive():
                process.kill()
                process.join(30)
    report["timings"] = [asdict(timing) for timing in timings]
    table = _table(report, timings)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "service.json").write_text(json.dumps(report, indent=2))
    (args.out / "service.md").write_text(table)
    print(table)
    return 0


def _batch_timings(field, remote, echo_session, batch: np.ndarray, repeats: int) -> list[Timing]:
    """One batch size of distance queries (adf): in-process, through the service, Zenoh alone, codec alone."""
    size = len(batch)
    wire = _query_sizes(batch)
    return [
        _time(f"query {size} pts, in-process", lambda _i: field.query(batch), repeats, per_item=size),
        _time(f"query {size} pts, service", lambda _i: remote.query(batch), repeats, per_item=size, sizes=wire),
        _time(f"query {size} pts, Zenoh echo", lambda _i: _echo(echo_session, *wire), repeats, sizes=wire),
        _time(f"query {size} pts, protocol codec", lambda _i: _codec(batch), repeats, per_item=size),
    ]


def _find_mesh(given: Path | None, defaults: tuple[Path, ...]) -> Path:
    candidates = [given] if given is not None else list(defaults)
    for path in candidates:
        if path.exists():
            return path
    raise SystemExit(f"badf bench service: no mesh at {', '.join(map(str, candidates))}; pass --mesh FILE.npz")


def _deforming_frames(vertices: np.ndarray, count: int) -> list[np.ndarray]:
    """A travelling wave of 1% of the bounding box across the mesh: a different vertex buffer each frame."""
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    frames = []
    for index in range(count):
        phase = 2.0 * np.pi * index / count
        wave = 0.01 * extent * np.sin(6.0 * vertices[:, 1] / extent + phase)
        frame = vertices.copy()
        frame[:, 0] += wave
        frames.append(frame.astype(np.float32))
    return frames


def _time(
    name: str, work: Callable[[int], object], count: int, *, per_item: int = 0, sizes: tuple[int, int] = (0, 0)
) -> Timing:
    for warm in range(min(5, count)):
        work(warm)
    samples = np.empty(count)
    started = time.perf_counter()
    for index in range(count):
        begin = time.perf_counter()
        work(index)
        samples[index] = time.perf_counter() - begin
    total = time.perf_counter() - started
    return Timing(
        name,
        count,
        float(np.median(samples) * 1e3),
        float(np.percentile(samples, 99) * 1e3),
        count / total,
        count * per_item / total,
        sizes[0],
        sizes[1],
    )


def _frame_size(vertices: np.ndarray) -> int:
    from badf.protocol import Frame, encode

    return len(encode(Frame("bench", 1, vertices)))


def _query_sizes(points: np.ndarray) -> tuple[int, int]:
    """Bytes of a distance query for `points` and of its reply."""
    from badf.protocol import QueryReply, QueryRequest, encode

    request = encode(QueryRequest("bench", points))
    return len(request), len(encode(QueryReply("bench", 1, distance=np.zeros(len(points), np.float32))))


def _codec(points: np.ndarray) -> None:
    """Encode and decode a query and its distance reply: the protocol's own CPU cost per round trip."""
    from badf.protocol import QueryReply, QueryRequest, decode, encode

    decode(bytes(encode(QueryRequest("bench", points))), QueryRequest)
    decode(bytes(encode(QueryReply("bench", 1, distance=points[:, 0]))), QueryReply)


def _echo(session, request_bytes: int, reply_bytes: int) -> None:
    payload = bytearray(max(request_bytes, 8))
    struct.pack_into("<Q", payload, 0, reply_bytes)
    for reply in session.get(_ECHO_KEY, payload=payload, timeout=60):
        reply.ok.payload.to_bytes()


def _echo_router(endpoint: str, ready) -> None:
    """A Zenoh router answering every query on bench/echo with as many bytes as the request's first 8 ask."""
    import signal
    import threading

    import zenoh

    from badf.protocol import zenoh_config

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    replies: dict[int, bytes] = {}

    def answer(query: zenoh.Query) -> None:
        size = struct.unpack_from("<Q", query.payload.to_bytes(), 0)[0]
        if size not in replies:
            replies[size] = bytes(size)
        query.reply(_ECHO_KEY, replies[size])
        query.drop()

    with zenoh.open(zenoh_config(mode="router", listen=[endpoint])) as session:
        session.declare_queryable(_ECHO_KEY, answer)
        ready.set()
        stop.wait()


def _wait(ready, process: multiprocessing.Process, what: str, timeout: float = 600.0) -> None:
    deadline = time.monotonic() + timeout
    while not ready.wait(0.1):
        if not process.is_alive():
            raise SystemExit(f"badf bench service: the {what} exited with status {process.exitcode}")
        if time.monotonic() > deadline:
            raise SystemExit(f"badf bench service: the {what} was not ready after {timeout:.0f} s")


def _free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def _table(report: dict, timings: list[Timing]) -> str:
    lines = [
        f"# badf service benchmark ({report['date']}, {report['host']}, device {report['device']})",
        "",
        f"Mesh {report['mesh']}: {report['vertices']} vertices, {report['faces']} faces, depth {report['depth']}; "
        f"round trip = update (one frame) + query of {report['round_trip_points']} points (distance, adf).",
        "",
        "| what | n | median ms | p99 ms | per second | Mpoints/s | request MB | reply MB |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for t in timings:
        lines.append(
            f"| {t.name} | {t.samples} | {t.median_ms:.3f} | {t.p99_ms:.3f} | {t.per_second:.1f} | "
            f"{t.points_per_second / 1e6:.2f} | {t.request_bytes / 1e6:.3f} | {t.reply_bytes / 1e6:.3f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m badf.bench._service", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
