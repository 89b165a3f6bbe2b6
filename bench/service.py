"""Service benchmark: what the protocol and Zenoh add on top of the engine.

    python -m badf.bench.service --mesh PATH.npz [--device cuda:0] [--small] [--out results.json]

On one device it times
  * the round trip "apply one frame of the deforming mesh, then answer a query of P points" (P = 65,536,
    distance, adf): median and p99 latency and round trips per second, through the service (a worker in
    its own process, reached over loopback TCP) beside the same two calls on the engine in this process;
  * distance queries of 1K to 1M points, service beside in-process: latency and points per second;
  * the floor under the service: Zenoh alone carrying the same request and reply sizes (an echo router in
    its own process), and the protocol's own encode + decode of the same messages.
Each figure is the median (and p99) of the timed repeats after 5 warm-up calls, measured at the caller:
what a client waits, Python included. `--small` sizes it for a CPU (20 round trips of 4,096 points,
batches up to 16K).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import platform
import socket
import struct
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Callable, Iterator

import numpy as np

from badf.bench._common import (
    bench_device_name,
    deform,
    fill_sized_defaults,
    print_table,
    start_warp,
    timestamp,
)
from badf.server._mesh_files import MESH_HELP, read_mesh

_SPAWN = multiprocessing.get_context("spawn")
_ECHO_KEY = "bench/echo"
_WARM_UP = 5
_FULL = {"points": 65_536, "round_trips": 300, "repeats": 30, "batches": "1024,4096,16384,65536,262144,1048576"}
_SMALL = {"points": 4096, "round_trips": 20, "repeats": 5, "batches": "1024,4096,16384"}


@dataclass
class Timing:
    what: str
    samples: int
    median_ms: float
    p99_ms: float
    per_second: float  # calls per second over the whole timed run
    points_per_second: float = 0.0
    request_bytes: int = 0
    reply_bytes: int = 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mesh", required=True, help=MESH_HELP)
    parser.add_argument("--device", default=None, help="cpu, cuda:0, ... (default: the first GPU, else cpu)")
    parser.add_argument("--depth", type=int, default=7, help="octree depth (default 7)")
    parser.add_argument("--small", action="store_true", help="CPU-sized defaults for the four flags below")
    parser.add_argument("--points", type=int, help="points per round-trip query (65,536; small: 4,096)")
    parser.add_argument("--round-trips", type=int, help="timed round trips (300; small: 20)")
    parser.add_argument("--batches", help="query batch sizes, comma-separated (1K..1M; small: 1K..16K)")
    parser.add_argument("--repeats", type=int, help="timed queries per batch size (30; small: 5)")
    parser.add_argument("--out", default=None, help="write the full results as JSON here")


def run(args: argparse.Namespace) -> int:
    from badf.server.adf import DistanceField

    device = start_warp(args.device)
    fill_sized_defaults(args, _SMALL, _FULL)
    batches = [int(size) for size in args.batches.split(",") if size]
    vertices, faces = read_mesh(args.mesh)
    frames = [deform(vertices, k / 32) for k in range(32)]
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    rng = np.random.default_rng(0)
    cloud = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), size=(max(batches + [args.points]), 3))
    cloud = cloud.astype(np.float32)
    points = cloud[: args.points]
    field = DistanceField(vertices, faces, depth=args.depth, device=device)
    report = {
        "benchmark": "service",
        "date": timestamp(),
        "device": bench_device_name(device),
        "host": platform.node(),
        "mesh": {"path": args.mesh, "vertices": len(vertices), "faces": len(faces)},
        "depth": args.depth,
        "round_trip_points": args.points,
    }
    with _service(device) as (client, echo):
        remote = client.register("bench", vertices, faces, depth=args.depth)
        wire = (_update_bytes(frames[0])[0] + _query_bytes(points)[0], _update_bytes(frames[0])[1] + _query_bytes(points)[1])

        def local_round(i: int) -> None:
            field.update(frames[i % len(frames)])
            field.query(points)

        def served_round(i: int) -> None:
            remote.update(frames[i % len(frames)])
            remote.query(points)

        def echo_round(_i: int) -> None:
            _echo(echo, *_update_bytes(frames[0]))
            _echo(echo, *_query_bytes(points))

        n = args.round_trips
        timings = [
            _time("round trip, in-process", local_round, n, per_item=args.points),
            _time("round trip, service", served_round, n, per_item=args.points, sizes=wire),
            _time("round trip, Zenoh echo of its bytes", echo_round, n, sizes=wire),
            _time("update, in-process", lambda i: field.update(frames[i % len(frames)]), n),
            _time("update, service", lambda i: remote.update(frames[i % len(frames)]), n, sizes=_update_bytes(frames[0])),
        ]
        for size in batches:
            timings += _batch_timings(field, remote, echo, cloud[:size], args.repeats)
        report["accuracy"] = _accuracy(field, remote, frames[0], faces, points)
        report["worker_field_stats"] = remote.info().field_stats
        remote.delete()
    report["timings"] = [asdict(timing) for timing in timings]
    print_table(
        f"service on {report['device']}, {args.mesh} ({len(faces)} triangles), depth {args.depth}; "
        f"round trip = update + {args.points}-point query",
        ["what", "n", "median ms", "p99 ms", "per s", "Mpoints/s", "request MB", "reply MB"],
        [
            [t.what, t.samples, round(t.median_ms, 3), round(t.p99_ms, 3), round(t.per_second, 1),
             round(t.points_per_second / 1e6, 2), round(t.request_bytes / 1e6, 3), round(t.reply_bytes / 1e6, 3)]
            for t in timings
        ],
    )  # fmt: skip
    accuracy = report["accuracy"]
    print(f"the times' accuracy: the service's ADF distances at {accuracy['points']} of the round trip's points against "
          f"the float64 oracle: {accuracy['max_error_diag']:.2e} / {accuracy['mean_error_diag']:.2e} diagonals (max / "
          f"mean); the same as in-process, bit for bit: {'yes' if accuracy['service_equals_in_process'] else 'NO'}")
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(report, handle, indent=2)
        print("wrote", args.out)
    return 0 if accuracy["service_equals_in_process"] else 1


def _accuracy(field, remote, vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> dict:
    """What the timed answers are worth: the served distances of one frame against the float64 oracle (on a
    sample: the oracle takes seconds per thousand points on a large mesh), and whether they equal the
    in-process engine's."""
    from badf.bench._oracle import ORACLE_SAMPLE, errors_against, signed_distance

    sample = points[:ORACLE_SAMPLE]
    remote.update(vertices)
    field.update(vertices)
    served = remote.query(sample).distance
    return {**errors_against(served, signed_distance(sample, vertices, faces), vertices), "mode": "adf",
            "service_equals_in_process": bool(np.array_equal(served, field.query(sample).distance))}


def _batch_timings(field, remote, echo, batch: np.ndarray, repeats: int) -> list[Timing]:
    """One batch size of distance queries: in-process, through the service, Zenoh alone, codec alone."""
    size = len(batch)
    wire = _query_bytes(batch)
    return [
        _time(f"query {size} pts, in-process", lambda _i: field.query(batch), repeats, per_item=size),
        _time(f"query {size} pts, service", lambda _i: remote.query(batch), repeats, per_item=size, sizes=wire),
        _time(f"query {size} pts, Zenoh echo", lambda _i: _echo(echo, *wire), repeats, sizes=wire),
        _time(f"query {size} pts, protocol codec", lambda _i: _codec(batch), repeats, per_item=size),
    ]


def _time(
    what: str, work: Callable[[int], object], count: int, *, per_item: int = 0, sizes: tuple[int, int] = (0, 0)
) -> Timing:
    for warm in range(_WARM_UP):
        work(warm)
    samples = np.empty(count)
    started = time.perf_counter()
    for index in range(count):
        begin = time.perf_counter()
        work(index)
        samples[index] = time.perf_counter() - begin
    total = time.perf_counter() - started
    return Timing(
        what,
        count,
        median_ms=float(np.median(samples) * 1e3),
        p99_ms=float(np.percentile(samples, 99) * 1e3),
        per_second=count / total,
        points_per_second=count * per_item / total,
        request_bytes=sizes[0],
        reply_bytes=sizes[1],
    )


def _update_bytes(vertices: np.ndarray) -> tuple[int, int]:
    """Bytes of a frame of `vertices`, and of the acknowledgement a blocking update waits for."""
    from badf.protocol import Frame, FrameAck, encode

    return len(encode(Frame("bench", 1, vertices))), len(encode(FrameAck("bench", 1)))


def _query_bytes(points: np.ndarray) -> tuple[int, int]:
    """Bytes of a distance query for `points`, and of its reply."""
    from badf.protocol import QueryReply, QueryRequest, encode

    reply = QueryReply("bench", 1, distance=np.zeros(len(points), np.float32))
    return len(encode(QueryRequest("bench", points))), len(encode(reply))


def _codec(points: np.ndarray) -> None:
    """Encode and decode a query and its distance reply: the protocol's own CPU cost per query."""
    from badf.protocol import QueryReply, QueryRequest, decode, encode

    decode(bytes(encode(QueryRequest("bench", points))), QueryRequest)
    decode(bytes(encode(QueryReply("bench", 1, distance=points[:, 0]))), QueryReply)


@contextmanager
def _service(device: str) -> Iterator[tuple]:
    """A worker process and an echo router process on free loopback ports; a client of each."""
    import zenoh

    from badf.client import Client
    from badf.protocol import zenoh_config
    from badf.server import WorkerSettings, end_process, worker_process

    endpoint, echo_endpoint = _free_endpoint(), _free_endpoint()
    settings = WorkerSettings(worker_id="bench", listen=(endpoint,), device=device, stats_interval_s=3600.0)
    echo_ready = _SPAWN.Event()
    echo_router = _SPAWN.Process(target=_echo_router, args=(echo_endpoint, echo_ready), daemon=True)
    echo_router.start()
    try:
        with worker_process(settings, start_timeout_s=600.0):
            if not echo_ready.wait(60):
                raise SystemExit("badf bench service: the echo router did not start within 60 s")
            echo_config = zenoh_config(mode="client", connect=[echo_endpoint], connect_timeout_s=60)
            with Client(endpoint, timeout=120) as client, zenoh.open(echo_config) as echo:
                yield client, echo
    finally:
        end_process(echo_router)


def _echo(session, request_bytes: int, reply_bytes: int) -> None:
    payload = bytearray(max(request_bytes, 8))
    struct.pack_into("<Q", payload, 0, reply_bytes)
    for reply in session.get(_ECHO_KEY, payload=payload, timeout=60):
        reply.ok.payload.to_bytes()


def _echo_router(endpoint: str, ready) -> None:
    """A Zenoh router answering each query on bench/echo with as many bytes as its first 8 bytes ask."""
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


def _free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def main() -> int:
    from badf.bench._cli import main_of

    return main_of("service")


if __name__ == "__main__":
    raise SystemExit(main())
