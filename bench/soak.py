"""Soak benchmark: many clients stream, update and query many objects on one worker for a bounded time,
and every answer is checked.

    python -m badf.bench.soak [--clients 8] [--objects 4] [--seconds 60] [--device cpu] [--out soak.json]

Each client is its own process (spawned) with its own Zenoh session. It registers its objects (a cube
whose faces are split into a grid), then, round after round until the time is up, for each object: streams
a few frames, sends one blocking update (the acknowledged frame), queries exactly and checks the answer,
and now and then asks for an ADF query, a slice and the object's info; each round it also queries one
object of another client. Frame F is the cube moved by offset(F) along x, so the exact distance at the probe
(2, 0, 0) is 1.5 - offset(F): a reply that names frame F must carry that distance, and a reply to the owner
right after the acknowledgement of F must name F (nobody else writes that object). At the end each owner
checks its objects' counters: the last acknowledged frame is the one applied, every frame it sent was
applied or dropped as stale (latest wins), none was rejected.

The worker's resident memory (VmRSS from /proc) is sampled every half second; the engine's device bytes
(object info, field_stats["device_bytes"] less the BVH build's arrays, which an object holds from a frame that
moves its domain to the next that keeps it, summed over the objects) and, on a GPU, the worker's GPU memory
as nvidia-smi reports it are read at the end of the warm-up and at the end. Bounded: `--seconds`,
`--max-rounds` per client, and a deadline for the whole run.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import platform
import socket
import subprocess
import threading
import time
from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np

from badf.bench._common import BenchFlagError, bench_device_name, print_table, timestamp

_SPAWN = multiprocessing.get_context("spawn")
PROBE = np.array([[2.0, 0.0, 0.0]], np.float32)
# The exact distance at the probe is 1.5 - offset(F) up to float32 rounding; offsets differ by 0.01.
ANSWER_TOLERANCE = 1e-4
_MAX_REPORTED = 20  # wrong answers and error messages kept per client


@dataclass(frozen=True)
class SoakSettings:
    clients: int = 8
    objects_per_client: int = 4
    seconds: float = 60.0
    warm_up_s: float | None = None  # default: a quarter of `seconds`, at least 5 s; and every client's first round
    device: str = "cpu"
    depth: int = 4
    grid: int = 8  # each cube face is split into grid x grid quads: 12 grid^2 triangles
    streams_per_update: int = 3
    max_rounds: int = 100_000  # per client
    request_timeout_s: float = 60.0
    start_timeout_s: float = 300.0

    @property
    def warm_up(self) -> float:
        return self.warm_up_s if self.warm_up_s is not None else max(5.0, self.seconds / 4)


@dataclass
class ClientTally:
    """What one client did and saw."""

    client: int
    rounds: int = 0
    updates_acknowledged: int = 0
    frames_streamed: int = 0
    exact_queries: int = 0
    adf_queries: int = 0
    slices: int = 0
    infos: int = 0
    peer_queries: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    error_samples: list[str] = field(default_factory=list)
    wrong_answers: list[str] = field(default_factory=list)
    final_failures: list[str] = field(default_factory=list)
    last_acknowledged: dict[str, int] = field(default_factory=dict)
    round_trip_ms: list[float] = field(default_factory=list)  # update + exact query, per object and round
    round_trip_at_s: list[float] = field(default_factory=list)  # when each began, in seconds after the start

    def wrong(self, text: str) -> None:
        if len(self.wrong_answers) < _MAX_REPORTED:
            self.wrong_answers.append(text)


def cube(grid: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed unit cube centred at the origin, each face split into grid x grid quads (outward normals)."""
    ticks = np.linspace(-0.5, 0.5, grid + 1)
    vertices, faces = [], []
    for axis in range(3):
        for side in (-0.5, 0.5):
            u, v = np.meshgrid(ticks, ticks, indexing="ij")
            plane = np.empty((grid + 1, grid + 1, 3))
            plane[..., axis], plane[..., (axis + 1) % 3], plane[..., (axis + 2) % 3] = side, u, v
            start = sum(len(block) for block in vertices)
            vertices.append(plane.reshape(-1, 3))
            index = start + np.arange((grid + 1) ** 2).reshape(grid + 1, grid + 1)
            a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
            quads = [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
            if side < 0:  # u x v points along +axis: flip the faces on the negative side
                quads = [q[:, ::-1] for q in quads]
            faces += quads
    return np.concatenate(vertices).astype(np.float32), np.concatenate(faces).astype(np.int32)


def offset(frame: int) -> float:
    """How far frame `frame` moves the cube along x: 13 distinct values, 0.01 apart, not in frame order."""
    return 0.01 * ((7 * frame) % 13)


def frame_vertices(base: np.ndarray, frame: int) -> np.ndarray:
    moved = base.copy()
    moved[:, 0] += offset(frame)
    return moved


def expected_probe_distance(frame: int) -> float:
    return 1.5 - offset(frame)


# --- a client process ---------------------------------------------------------------------------------


def _client_main(endpoint: str, index: int, settings: SoakSettings, barrier, warm, results) -> None:
    """Register, wait for everyone, run rounds until the time or the round count is up, check, report."""
    from badf.client import Client
    from badf.protocol import BadfError

    tally = ClientTally(index)
    base, faces = cube(settings.grid)
    rng = np.random.default_rng(index)
    peers = [f"c{c}-o{o}" for c in range(settings.clients) for o in range(settings.objects_per_client)]
    started = False
    try:
        with Client(endpoint, timeout=settings.request_timeout_s) as client:
            objects = [
                # rigid off: the frames are shifts, which rigid="auto" would keep; the soak holds the rebuilds
                client.register(f"c{index}-o{o}", base, faces, depth=settings.depth, rigid="off")
                for o in range(settings.objects_per_client)
            ]
            sent = {obj.name: 0 for obj in objects}
            seen_peer_frames: dict[str, int] = {}
            barrier.wait(settings.start_timeout_s)
            started = True
            began = time.monotonic()
            deadline = began + settings.seconds
            while time.monotonic() < deadline and tally.rounds < settings.max_rounds:
                for obj in objects:
                    try:
                        _one_round(obj, base, rng, tally, sent, settings, began)
                    except BadfError as error:
                        _count_error(tally, error, obj.name)
                try:
                    _peer_query(client, peers[rng.integers(len(peers))], seen_peer_frames, tally)
                except BadfError as error:
                    _count_error(tally, error, "peer")
                tally.rounds += 1
                if tally.rounds == 1:
                    warm.release()  # every object of this client has had each kind of request once
            for obj in objects:
                _final_check(obj, sent[obj.name], tally)
    except BadfError as error:  # registration or the final check could not be made
        _count_error(tally, error, "registration" if not started else "final check")
    except threading.BrokenBarrierError:
        tally.final_failures.append("the run did not start: another client failed to register")
    finally:
        if not started:
            barrier.abort()  # nobody waits for a client that will not come
        results.put(asdict(tally))


def _one_round(obj, base: np.ndarray, rng, tally: ClientTally, sent: dict[str, int], settings: SoakSettings,
               began: float) -> None:
    for _ in range(settings.streams_per_update):
        obj.stream(frame_vertices(base, obj.frame + 1))
        sent[obj.name] += 1
        tally.frames_streamed += 1
    tally.round_trip_at_s.append(time.monotonic() - began)
    started = time.perf_counter()
    next_frame = obj.frame + 1
    sent[obj.name] += 1
    acknowledged = obj.update(frame_vertices(base, next_frame))
    if acknowledged != next_frame:
        tally.wrong(f"{obj.name}: update of frame {next_frame} acknowledged as {acknowledged}")
    tally.updates_acknowledged += 1
    tally.last_acknowledged[obj.name] = acknowledged
    reply = obj.query(PROBE, mode="exact")
    tally.round_trip_ms.append((time.perf_counter() - started) * 1e3)
    tally.exact_queries += 1
    if reply.frame != acknowledged:
        tally.wrong(f"{obj.name}: query after the acknowledgement of frame {acknowledged} answered frame {reply.frame}")
    if abs(float(reply.distance[0]) - expected_probe_distance(reply.frame)) > ANSWER_TOLERANCE:
        tally.wrong(
            f"{obj.name}: frame {reply.frame} answered {float(reply.distance[0])!r} at the probe, "
            f"expected {expected_probe_distance(reply.frame)!r}"
        )
    if tally.rounds % 5 == 0:
        points = rng.uniform(-1.0, 1.0, size=(256, 3)).astype(np.float32)
        adf = obj.query(points, mode="adf", outputs=("distance", "normal"))
        tally.adf_queries += 1
        if adf.frame != acknowledged or not (np.isfinite(adf.distance).all() and np.isfinite(adf.normal).all()):
            tally.wrong(f"{obj.name}: ADF query of frame {adf.frame} (expected {acknowledged}) or not finite")
    if tally.rounds % 10 == 0:
        cut = obj.slice("z", 0.0, resolution=32, levels=(0, settings.depth))
        tally.slices += 1
        if cut.frame != acknowledged or not np.isfinite(cut.grid).all():
            tally.wrong(f"{obj.name}: slice of frame {cut.frame} (expected {acknowledged}) or not finite")
        info = obj.info()
        tally.infos += 1
        if info.frame != acknowledged or info.frames_rejected:
            tally.wrong(f"{obj.name}: info says frame {info.frame} and {info.frames_rejected} rejected")


def _peer_query(client, name: str, seen: dict[str, int], tally: ClientTally) -> None:
    """Query any object (maybe another client's, changing meanwhile): its answer must fit the frame it names,
    and the frames one object answers with never go backwards."""
    reply = client.object(name).query(PROBE, mode="exact")
    tally.peer_queries += 1
    if abs(float(reply.distance[0]) - expected_probe_distance(reply.frame)) > ANSWER_TOLERANCE:
        tally.wrong(f"peer {name}: frame {reply.frame} answered {float(reply.distance[0])!r}")
    if reply.frame < seen.get(name, 0):
        tally.wrong(f"peer {name}: answered frame {reply.frame} after frame {seen[name]}")
    seen[name] = reply.frame


def _final_check(obj, sent: int, tally: ClientTally) -> None:
    info = obj.info()
    acknowledged = tally.last_acknowledged.get(obj.name, 0)
    problems = []
    if info.frame != acknowledged:
        problems.append(f"frame {info.frame}, last acknowledged {acknowledged}")
    if info.frames_applied + info.frames_dropped != sent:
        problems.append(f"{info.frames_applied} applied + {info.frames_dropped} dropped, {sent} sent")
    if info.frames_rejected or info.last_error is not None:
        problems.append(f"{info.frames_rejected} rejected, last error {info.last_error!r}")
    if problems:
        tally.final_failures.append(f"{obj.name}: " + "; ".join(problems))


def _count_error(tally: ClientTally, error: Exception, where: str) -> None:
    name = type(error).__name__
    tally.errors[name] = tally.errors.get(name, 0) + 1
    if len(tally.error_samples) < _MAX_REPORTED:
        tally.error_samples.append(f"{where}: {name}: {error}")


# --- the run ------------------------------------------------------------------------------------------


@dataclass
class SoakReport:
    settings: dict
    device: str
    seconds_run: float
    clients: list[dict]
    totals: dict[str, int]
    errors: dict[str, int]
    wrong_answers: list[str]
    final_failures: list[str]
    rss_mib: dict[str, float]  # worker VmRSS: after registration, at the end of the warm-up, max after it, end
    device_bytes: dict[str, int]  # engine device bytes summed over the objects (less rebuild arrays): warm-up end, end
    gpu_memory_mib: dict[str, float | None]  # the worker's GPU memory as nvidia-smi sees it (None: no GPU)
    round_trip_ms: dict[str, float]  # update + exact query: median, p99, max, and max of rounds after the warm-up
    worker_exit_code: int | None = None
    date: str = ""
    host: str = ""

    @property
    def rss_growth_mib(self) -> float:
        return self.rss_mib["max_after_warm_up"] - self.rss_mib["warm_up_end"]

    @property
    def device_bytes_growth(self) -> int:
        return self.device_bytes["end"] - self.device_bytes["warm_up_end"]


def run_soak(settings: SoakSettings, *, log=print) -> SoakReport:
    """Start a worker and the clients, run, collect; the worker and clients are ended whatever happens."""
    import warp as wp

    from badf.client import Client
    from badf.server import WorkerSettings, end_process, worker_process

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # the device's name is read for the report
    endpoint = _free_endpoint()
    worker_settings = WorkerSettings(
        worker_id="soak", listen=(endpoint,), device=settings.device, stats_interval_s=max(5.0, settings.seconds / 6)
    )
    barrier = _SPAWN.Barrier(settings.clients + 1)
    warm = _SPAWN.Semaphore(0)  # released by each client after its first round
    results = _SPAWN.Queue()
    with worker_process(worker_settings, start_timeout_s=settings.start_timeout_s) as worker:
        sampler = _RssSampler(worker.pid)
        sampler.start()
        clients = [
            _SPAWN.Process(target=_client_main, args=(endpoint, index, settings, barrier, warm, results), daemon=True)
            for index in range(settings.clients)
        ]
        for process in clients:
            process.start()
        try:
            with Client(endpoint, timeout=settings.request_timeout_s) as monitor:
                try:
                    barrier.wait(settings.start_timeout_s)  # every object is registered
                except threading.BrokenBarrierError:
                    tallies = _collect(results, clients, deadline=time.monotonic() + 60)
                    reasons = [text for tally in tallies for text in tally["error_samples"]]
                    raise RuntimeError(f"the soak did not start: {reasons or 'a client did not register in time'}")
                started = time.monotonic()
                rss_registered = sampler.latest()
                log(f"soak: {settings.clients} clients x {settings.objects_per_client} objects, {settings.seconds:g} s")
                _wait(started + settings.warm_up, clients)
                if not _wait_for_first_rounds(warm, settings.clients, started + settings.seconds / 2):
                    log("soak: the warm-up ended at half the run, before every client's first round")
                rss_warm = sampler.latest()
                sampler.mark_warm_up_end()
                device_warm = _device_bytes(monitor)
                gpu_warm = _gpu_memory_mib(worker.pid)
                tallies = _collect(results, clients, deadline=started + settings.seconds + settings.start_timeout_s)
                seconds_run = time.monotonic() - started
                rss_end = sampler.latest()
                rss_max = max(sampler.max_after_warm_up(), rss_end)
                device_end = _device_bytes(monitor)
                gpu_end = _gpu_memory_mib(worker.pid)
                for info in monitor.objects():
                    monitor.object(info.name).delete()
        finally:
            sampler.stop()
            for process in clients:
                end_process(process, grace_s=10.0)
    return _report(
        settings, tallies, seconds_run,
        rss={"registered": rss_registered, "warm_up_end": rss_warm,
             "max_after_warm_up": rss_max, "end": rss_end},
        device_bytes={"warm_up_end": device_warm, "end": device_end},
        gpu_memory_mib={"warm_up_end": gpu_warm, "end": gpu_end},
        worker_exit_code=worker.exitcode,
    )  # fmt: skip


def _wait(until: float, clients: list) -> None:
    """Until the monotonic time `until`, or until every client has exited (then the run is over early)."""
    while time.monotonic() < until and any(process.is_alive() for process in clients):
        time.sleep(min(0.2, max(0.0, until - time.monotonic())))


def _wait_for_first_rounds(warm, clients: int, until: float) -> bool:
    """Until every client has finished its first round, or the monotonic time `until`; whether they all
    had. A round's first slice and ADF query size the object's query buffers, so memory is compared only
    after every object's (a client slowed at the start once finished it after a 5 s warm-up, and its
    object's first slice read as 143,652 device bytes of growth)."""
    for _ in range(clients):
        if not warm.acquire(timeout=max(0.0, until - time.monotonic())):
            return False
    return True


def _collect(results, clients: list, *, deadline: float) -> list[dict]:
    import queue

    tallies = []
    while len(tallies) < len(clients):
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError(f"only {len(tallies)} of {len(clients)} soak clients reported before the deadline")
        try:
            tallies.append(results.get(timeout=min(remaining, 1.0)))
        except queue.Empty:
            if not any(process.is_alive() for process in clients) and results.empty():
                raise RuntimeError(f"{len(clients) - len(tallies)} soak clients exited without a report") from None
    return sorted(tallies, key=lambda tally: tally["client"])


def _gpu_memory_mib(pid: int) -> float | None:
    """The GPU memory nvidia-smi reports for process `pid` (MiB), or None without nvidia-smi or a GPU."""
    try:
        listing = subprocess.run(
            ["nvidia-smi", "--query-compute-apps=pid,used_memory", "--format=csv,noheader,nounits"],
            capture_output=True, text=True, timeout=30, check=True,
        ).stdout  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    for line in listing.splitlines():
        fields = [field.strip() for field in line.split(",")]
        if len(fields) == 2 and fields[0] == str(pid):
            return float(fields[1])
    return None


def _device_bytes(monitor) -> int:
    """The engine's device bytes over the objects, less what only a BVH build uses: an object holds that from a
    frame that moves the domain to the next one that keeps it, so it comes and goes with the cube's motion, and
    a read after a move would count it as growth."""
    total = 0
    for info in monitor.objects():
        stats = info.field_stats
        total += int(stats.get("device_bytes", 0)) - int(stats.get("memory_bytes", {}).get("rebuild", 0))
    return total


class _RssSampler:
    """Samples a process's VmRSS (MiB) every half second on a thread."""

    def __init__(self, pid: int) -> None:
        self._path = f"/proc/{pid}/status"
        self._samples: list[float] = []
        self._warm_up_index: int | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)

    def start(self) -> None:
        self._samples.append(self._read())
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            value = self._read()
            if value > 0:
                self._samples.append(value)

    def _read(self) -> float:
        try:
            with open(self._path) as status:
                for line in status:
                    if line.startswith("VmRSS:"):
                        return int(line.split()[1]) / 1024.0
        except OSError:  # the process is gone
            pass
        return 0.0

    def latest(self) -> float:
        value = self._read()
        return value if value > 0 else self._samples[-1]

    def mark_warm_up_end(self) -> None:
        self._warm_up_index = len(self._samples)

    def max_after_warm_up(self) -> float:
        return max(self._samples[self._warm_up_index or 0 :] + [self.latest()])


def _report(
    settings: SoakSettings, tallies: list[dict], seconds_run: float, *, rss, device_bytes, gpu_memory_mib,
    worker_exit_code,
) -> SoakReport:
    totals: Counter = Counter()
    errors: Counter = Counter()
    wrong, failures, round_trips, round_trips_at = [], [], [], []
    for tally in tallies:
        for name in ("rounds", "updates_acknowledged", "frames_streamed", "exact_queries", "adf_queries", "slices",
                     "infos", "peer_queries"):  # fmt: skip
            totals[name] += tally[name]
        errors.update(tally["errors"])
        wrong += [f"client {tally['client']}: {text}" for text in tally["wrong_answers"]]
        failures += [f"client {tally['client']}: {text}" for text in tally["final_failures"]]
        failures += [f"client {tally['client']}: {text}" for text in tally["error_samples"]]
        round_trips += tally["round_trip_ms"]
        round_trips_at += tally["round_trip_at_s"]
    if len(tallies) < settings.clients:  # a client process that died sends none
        failures.append(f"{settings.clients - len(tallies)} of {settings.clients} clients reported nothing (they died)")
    if totals["rounds"] == 0:
        failures.append("no client finished a round: the soak checked nothing")
    samples = np.asarray(round_trips) if round_trips else np.zeros(1)
    after_warm_up = samples[np.asarray(round_trips_at) >= settings.warm_up] if round_trips else samples
    after_warm_up = after_warm_up if len(after_warm_up) else np.zeros(1)
    for tally in tallies:
        del tally["round_trip_ms"], tally["round_trip_at_s"]  # kept only as percentiles
    return SoakReport(
        settings=asdict(settings), device=bench_device_name(settings.device), seconds_run=round(seconds_run, 2),
        clients=tallies, totals=dict(totals), errors=dict(errors), wrong_answers=wrong, final_failures=failures,
        rss_mib={key: round(value, 1) for key, value in rss.items()}, device_bytes=device_bytes,
        gpu_memory_mib=gpu_memory_mib,
        round_trip_ms={"median": round(float(np.median(samples)), 2),
                       "p99": round(float(np.percentile(samples, 99)), 2), "max": round(float(samples.max()), 2),
                       "max_after_warm_up": round(float(after_warm_up.max()), 2)},
        worker_exit_code=worker_exit_code, date=timestamp(), host=platform.node(),
    )  # fmt: skip


def _free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


# --- command line -------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = SoakSettings()
    parser.add_argument("--clients", type=int, default=defaults.clients, help="client processes (default 8)")
    parser.add_argument("--objects", type=int, default=defaults.objects_per_client, help="objects per client (4)")
    parser.add_argument("--seconds", type=float, default=defaults.seconds, help="how long the clients run (60)")
    parser.add_argument("--warm-up", type=float, default=None, help="seconds before memory is compared (a quarter of --seconds, at least 5; "
                        "and until every client has finished a round, up to half the run)")
    parser.add_argument("--device", default=defaults.device, help="the worker's device: cpu, cuda:0, ... (cpu)")
    parser.add_argument("--depth", type=int, default=defaults.depth, help="octree depth of every object (4)")
    parser.add_argument("--grid", type=int, default=defaults.grid, help="cube faces split grid x grid (8)")
    parser.add_argument("--max-rounds", type=int, default=defaults.max_rounds, help="rounds per client at most")
    parser.add_argument("--out", default=None, help="write the report as JSON here")


def run(args: argparse.Namespace) -> int:
    settings = SoakSettings(
        clients=args.clients, objects_per_client=args.objects, seconds=args.seconds, warm_up_s=args.warm_up,
        device=args.device, depth=args.depth, grid=args.grid, max_rounds=args.max_rounds,
    )  # fmt: skip
    if args.warm_up is not None and args.warm_up >= settings.seconds:  # it measured memory after the run instead
        raise BenchFlagError(f"--warm-up ({args.warm_up:g} s) must be shorter than --seconds ({settings.seconds:g})")
    report = run_soak(settings)
    print_summary(report)
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(asdict(report), handle, indent=2)
        print("wrote", args.out)
    held = not (report.errors or report.wrong_answers or report.final_failures)
    return 0 if held else 1


def print_summary(report: SoakReport) -> None:
    s, t = report.settings, report.totals
    rt = report.round_trip_ms
    rows = [
        ["clients x objects", f"{s['clients']} x {s['objects_per_client']}"],
        ["seconds run (warm-up)", f"{report.seconds_run} ({s['warm_up_s'] or max(5.0, s['seconds'] / 4):g})"],
        ["updates acknowledged", t.get("updates_acknowledged", 0)],
        ["frames streamed", t.get("frames_streamed", 0)],
        ["queries exact / adf / peer", f"{t.get('exact_queries', 0)} / {t.get('adf_queries', 0)} / "
                                       f"{t.get('peer_queries', 0)}"],
        ["slices / infos", f"{t.get('slices', 0)} / {t.get('infos', 0)}"],
        ["round trip ms median / p99 / max (after warm-up)",
         f"{rt['median']} / {rt['p99']} / {rt['max']} ({rt['max_after_warm_up']})"],
        ["error replies", sum(report.errors.values())],
        ["wrong answers", len(report.wrong_answers)],
        ["final check failures", len(report.final_failures)],
        ["worker RSS MiB registered / warm / max after / end",
         " / ".join(str(report.rss_mib[k]) for k in ("registered", "warm_up_end", "max_after_warm_up", "end"))],
        ["device bytes warm / end", f"{report.device_bytes['warm_up_end']:,} / {report.device_bytes['end']:,}"],
        ["GPU MiB (nvidia-smi) warm / end", f"{report.gpu_memory_mib['warm_up_end']} / {report.gpu_memory_mib['end']}"],
    ]  # fmt: skip
    print_table(f"soak on {report.device}, {report.date}", ["what", "value"], rows)
    for text in (report.wrong_answers + report.final_failures)[:10]:
        print("  !", text)


def main() -> int:
    from badf.bench._cli import main_of

    return main_of("soak")


if __name__ == "__main__":
    raise SystemExit(main())
