"""`badf demo [morph|cloth]`: a worker, a streaming client and the viewer, on an embedded default.

morph (the default): a built-in shape deforms frame by frame (or `--mesh FILE` with a built-in wobble, or
`--sequence FILE.npz` of recorded frames); each frame is sent to the worker, then a batch of points is
queried, and one line reports frames per second, update and query times, and the ADF's error on a
sample against exact queries.
cloth: the paper's sphere-cloth scene; the client simulates a 16K-triangle cloth hanging from two corners
and takes penalty forces from batched queries of a moving 1K-triangle sphere's field (`--stiff`: a
stiffness and time step at which an explicit penalty diverges).
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import pathlib
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack

import numpy as np

from badf.cli._extras import missing_extra
from badf.protocol import (
    DEFAULT_ENDPOINT,
    DEFAULT_LIMITS,
    MAX_NAME_LENGTH,
    BadfError,
    InvalidOptionError,
    WorkerUnavailableError,
    zenoh_config,
)
from badf.protocol._session import with_a_free_port
from badf.server._cuda import device_problem
from badf.server._mesh_files import MeshFileError, read_frames, read_mesh
from badf.server._signals import on_stop_signals

# Depth when none is given: what keeps frames interactive on each kind of device.
DEFAULT_DEPTH = {"cuda": 7, "cpu": 5}
CLOTH_SPHERE_DEPTH = {"cuda": 7, "cpu": 5}
DEFAULT_POINTS = 8192  # morph: points queried per frame
# How long a frame refused by a worker that is going away waits for the stop signal that may have sent it
# there (_StopFlag.frame): the signal reaches this process at the same moment, so a fraction of this.
_STOP_GRACE_S = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__.split("\n\n")[0]
    parser.add_argument("scene", nargs="?", choices=("morph", "cloth"), default="morph",
                        help="morph: a deforming shape (default); cloth: the sphere-cloth scene")
    parser.add_argument("--frames", type=int, default=None, metavar="N", help="stop after N frames (default: Ctrl-C)")
    parser.add_argument("--mesh", default=None, metavar="FILE",
                        help="morph: any mesh file trimesh reads, wobbled in place (default: a built-in shape)")
    parser.add_argument("--sequence", default=None, metavar="FILE.npz",
                        help="morph: recorded frames, an .npz with vertices (T, N, 3) and faces (M, 3); loops")
    parser.add_argument("--device", default=None,
                        help="worker device, e.g. cuda:0 or cpu (default: the first GPU if there is one, else cpu)")
    parser.add_argument("--depth", type=int, default=None,
                        help=f"octree depth (default: {DEFAULT_DEPTH['cuda']} on a GPU, {DEFAULT_DEPTH['cpu']} on the CPU)")
    parser.add_argument("--points", type=int, default=None, metavar="N", help=f"morph: points queried per frame ({DEFAULT_POINTS})")
    parser.add_argument("--stiff", action="store_true",
                        help="cloth: penalty stiffness 5e4 N/m per particle with one 1/60 s step per frame")
    parser.add_argument("--listen", default=DEFAULT_ENDPOINT, metavar="ENDPOINT",
                        help=f"the worker's (router's) endpoint (default: {DEFAULT_ENDPOINT})")
    parser.add_argument("--no-viewer", action="store_true", help="run without the web viewer (headless)")
    parser.add_argument("--host", default="127.0.0.1", help="viewer web page host (default: 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="viewer web page port (default: 8080)")


def run(args: argparse.Namespace) -> int:
    # before anything starts: without viser the worker was started, then the viewer died in a traceback
    missing = missing_extra("badf demo", ("warp", "trimesh"), "server")
    viewer_missing = None if args.no_viewer else missing_extra("badf demo", ("viser",), "viewer")
    if missing is None and viewer_missing is not None:
        missing = f"{viewer_missing}, or pass --no-viewer"
    if missing is not None:
        print(missing, file=sys.stderr)
        return 2
    if args.frames is not None and args.frames < 1:
        print("badf demo: --frames must be at least 1", file=sys.stderr)
        return 2
    if args.mesh is not None and args.sequence is not None:
        print("badf demo: give --mesh or --sequence, not both", file=sys.stderr)
        return 2
    # a flag of the other scene was run as if absent (outside check, 2026-11-22)
    other_scene = {"cloth": (("--mesh", args.mesh), ("--sequence", args.sequence), ("--points", args.points)),
                   "morph": (("--stiff", args.stiff or None),)}[args.scene]
    for flag, value in other_scene:
        if value is not None:
            print(f"badf demo {args.scene}: {flag} is for the {'morph' if args.scene == 'cloth' else 'cloth'} scene",
                  file=sys.stderr)
            return 2
    if args.points is None:
        args.points = DEFAULT_POINTS
    if not 1 <= args.points <= DEFAULT_LIMITS.max_points:
        print(f"badf demo: --points must be in 1..{DEFAULT_LIMITS.max_points}, got {args.points}", file=sys.stderr)
        return 2
    if not 0 <= args.port <= 65535:
        print(f"badf demo: --port must be in 0..65535, got {args.port}", file=sys.stderr)
        return 2
    try:
        zenoh_config(mode="router", listen=[args.listen])  # checks the endpoint's form, as serve does
        args.listen = with_a_free_port(args.listen)  # port 0: one chosen now, which the worker, client and viewer share
    except InvalidOptionError as error:
        print(f"badf demo: --listen: {error}", file=sys.stderr)
        return 2
    from badf.server.adf._tolerances import MAX_DEPTH

    if args.depth is not None and not 1 <= args.depth <= MAX_DEPTH:
        print(f"badf demo: --depth must be in 1..{MAX_DEPTH}, got {args.depth}", file=sys.stderr)
        return 2
    try:  # the mesh files are read before anything starts, so a bad one costs nothing
        source = _morph_source(args) if args.scene == "morph" else None
    except MeshFileError as error:
        print(f"badf demo: {error}", file=sys.stderr)
        return 2
    device = _default_device() if args.device is None else args.device
    problem = device_problem(device)
    if problem is None and not args.no_viewer:
        problem = _host_problem(args.host)
    if problem is not None:
        print(f"badf demo: {problem}", file=sys.stderr)
        return 2
    kind = "cuda" if device.startswith("cuda") else "cpu"
    chosen = args.depth is not None
    depth = args.depth if chosen else (CLOTH_SPHERE_DEPTH if args.scene == "cloth" else DEFAULT_DEPTH)[kind]
    print(f"badf demo {args.scene}: worker on {device}, octree depth {depth}"
          + ("" if chosen else f" (the default on {'a GPU' if kind == 'cuda' else 'the CPU'}; --depth to change)"))
    # Ctrl-C and SIGTERM end the loop; the stack then ends the viewer and the worker, by their pids
    stop = _StopFlag()
    with ExitStack() as stack:
        try:
            _start_worker(stack, args.listen, device)
        except BadfError as error:
            print(f"badf demo: the worker did not start: {error}", file=sys.stderr)
            return 1
        if not args.no_viewer:
            _start_viewer(stack, args.listen, args.host, args.port)
        from badf.client import Client

        client = stack.enter_context(Client(args.listen, timeout=120.0))
        try:
            if args.scene == "cloth":
                return _run_cloth(client, args, depth, stop, with_viewer=not args.no_viewer)
            return _run_morph(client, args, source, depth, stop)
        except BadfError as error:
            print(f"\nbadf demo: {error}", file=sys.stderr)
            return 1


class _StopFlag:
    def __init__(self) -> None:
        self.stopped = False
        on_stop_signals(self._stop)

    def _stop(self, _signum, _frame) -> None:
        self.stopped = True

    @contextlib.contextmanager
    def frame(self) -> Iterator[None]:
        """One frame of a scene's loop. A stop signal sent to the whole process group (`timeout`, a service
        manager, `kill -TERM -- -PGID`) reaches the demo's worker too, which may refuse the request in flight
        before this process has run its handler (the demo then exited 1 with "its worker is gone" instead of its
        summary; eighteenth outside check). Such a refusal ends the frame, and the loop, as the signal does."""
        try:
            yield
        except WorkerUnavailableError:
            if not self._arrives(_STOP_GRACE_S):
                raise

    def _arrives(self, within_s: float) -> bool:
        """Whether a stop signal has come, or comes within `within_s` seconds."""
        deadline = time.monotonic() + within_s
        while not self.stopped and time.monotonic() < deadline:
            time.sleep(0.01)  # polling: the handler runs between sleeps, and the flag decides
        return self.stopped


def _default_device() -> str:
    try:
        import warp as wp

        wp.config.log_level = wp.LOG_ERROR
        wp.init()
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    except ImportError:
        return "cpu"


def _host_problem(host: str) -> str | None:
    """Why the viewer could not serve its page on `host`, or None (also when the viewer is not installed)."""
    try:
        from badf.web_viewer._viewer import check_host
    except ImportError:
        return None
    try:
        check_host(host)
    except ValueError as error:
        return f"--host: {error}"
    return None


def _start_worker(stack: ExitStack, endpoint: str, device: str) -> None:
    from badf.server import WorkerSettings, worker_process

    print("starting the worker (the first run compiles its kernels, which takes a minute on the CPU) ...",
          flush=True)
    started = time.perf_counter()
    stack.enter_context(worker_process(WorkerSettings(device=device, listen=(endpoint,), stats_interval_s=60.0)))
    print(f"worker ready on {endpoint} after {time.perf_counter() - started:.1f} s", flush=True)


def _start_viewer(stack: ExitStack, endpoint: str, host: str, port: int) -> None:
    from badf.web_viewer import viewer_process

    url = stack.enter_context(viewer_process(connect=endpoint, host=host, port=port))
    print(f"viewer: open {url} in a browser", flush=True)


# -- morph -----------------------------------------------------------------------------------------------
def _run_morph(client, args, source, depth: int, stop: _StopFlag) -> int:
    frames_of, faces, name = source
    rest = frames_of(0)
    rng = np.random.default_rng(0)
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    diag = float(np.linalg.norm((hi - lo).astype(np.float64)))  # float32's square of a 1e-39 mesh's extent is 0
    obj = client.register(name, rest, faces, depth=depth, sign="auto", replace=True)
    print(f"registered {name!r}: {len(rest)} vertices, {len(faces)} triangles; querying {args.points} points a frame")
    frame_times, update_times, query_times, errors = [], [], [], []
    frame = 0
    while not stop.stopped and (args.frames is None or frame < args.frames):
        frame += 1
        with stop.frame():
            start = time.perf_counter()
            vertices = frames_of(frame)
            obj.update(vertices)
            updated = time.perf_counter()
            centre = (vertices.max(axis=0) + vertices.min(axis=0)) / 2
            points = (centre + (rng.random((args.points, 3)) - 0.5) * (hi - lo) * 1.3).astype(vertices.dtype)
            result = obj.query(points, mode="adf", outputs=("distance", "normal"))
            done = time.perf_counter()
            if frame % 10 == 1:  # the ADF against exact queries on a sample, every tenth frame
                sample = points[:256]
                exact = obj.query(sample, mode="exact").distance
                errors.append(float(np.max(np.abs(result.distance[:256] - exact)) / diag))
            frame_times.append(done - start)
            update_times.append(updated - start)
            query_times.append(done - updated)
        if stop.stopped:
            break
        _live(f"frame {frame:5d} (worker frame {result.frame}) | {1.0 / np.mean(frame_times[-30:]):6.1f} fps | "
              f"update {1e3 * update_times[-1]:7.2f} ms | query {1e3 * query_times[-1]:7.2f} ms | "
              f"ADF max error {errors[-1]:.2e} diagonals")
    print()
    if frame_times:
        print(f"summary: {len(frame_times)} frames, median update {1e3 * np.median(update_times):.2f} ms, "
              f"median query ({args.points} points) {1e3 * np.median(query_times):.2f} ms, "
              f"{1.0 / np.median(frame_times):.1f} frames/s, ADF max error on samples {max(errors):.2e} diagonals")
    return 0


def _morph_source(args):
    """(frame -> vertices, faces, object name)."""
    if args.sequence is not None:
        frames, faces = read_frames(args.sequence)
        return (lambda k: frames[k % len(frames)]), faces, _key_safe(pathlib.Path(args.sequence).stem)
    if args.mesh is not None:
        vertices, faces = read_mesh(args.mesh)
        name = pathlib.Path(args.mesh).stem
    else:
        import trimesh

        shape = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
        vertices, faces = np.asarray(shape.vertices, np.float32), np.asarray(shape.faces, np.int32)
        name = "blob"
    return (lambda k: _wobble(vertices, k)), faces, _key_safe(name)


def _wobble(vertices: np.ndarray, frame: int) -> np.ndarray:
    """A smooth, travelling deformation: radial bulges about the centre, a few percent of the size; in the mesh's
    own precision (float64 stays float64: far from the origin float32 would weld its vertices)."""
    centre = (vertices.max(axis=0) + vertices.min(axis=0)) / 2
    offset = vertices - centre
    size = float(np.max(np.linalg.norm(offset, axis=1))) or 1.0
    u = offset / size
    t = 0.08 * frame
    bulge = 0.18 * np.sin(3.0 * u[:, 0] + t) * np.cos(2.0 * u[:, 1] - 1.3 * t) + 0.1 * np.sin(4.0 * u[:, 2] + 0.7 * t)
    twist = 0.6 * np.sin(0.5 * t) * u[:, 2]
    c, s = np.cos(twist), np.sin(twist)
    x, y = offset[:, 0] * c - offset[:, 1] * s, offset[:, 0] * s + offset[:, 1] * c
    moved = np.stack([x, y, offset[:, 2]], axis=1) * (1.0 + bulge)[:, None]
    return (centre + moved).astype(vertices.dtype)


def _key_safe(name: str) -> str:
    """An object name made from a file name: ASCII letters, digits, '-' and '_' (others become '_'), cut to
    the names' 100 characters."""
    safe = "".join(ch if (ch.isascii() and ch.isalnum()) or ch in "-_" else "_" for ch in name)
    return safe[:MAX_NAME_LENGTH] or "mesh"


# -- cloth -----------------------------------------------------------------------------------------------
def _run_cloth(client, args, depth: int, stop: _StopFlag, *, with_viewer: bool) -> int:
    import trimesh

    from badf.server._cloth import Cloth, ClothSettings, SphereMotion

    settings = ClothSettings.stiff() if args.stiff else ClothSettings()
    motion = SphereMotion()
    shape = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    unit, sphere_faces = np.asarray(shape.vertices, np.float32), np.asarray(shape.faces, np.int32)
    cloth = Cloth(settings)
    sphere = client.register("sphere", unit * motion.radius + motion.centre(0.0), sphere_faces, depth=depth,
                             sign="auto", replace=True)
    # the cloth itself is only registered for the viewer to draw it: unsigned, as an open sheet
    sheet = client.register("cloth", cloth.positions.astype(np.float32), cloth.faces, depth=max(depth - 1, 1),
                            sign="none", replace=True) if with_viewer else None
    print(f"cloth: {len(cloth.positions)} particles, {len(cloth.faces)} triangles; sphere: {len(sphere_faces)} "
          f"triangles; penalty {settings.penalty_stiffness:g} N/m, {settings.substeps} substep(s) of "
          f"{1e3 * settings.frame_time / settings.substeps:.2f} ms (omega*dt {settings.explicit_stability_number:.2f}"
          f"{': an explicit step would diverge' if settings.explicit_stability_number > 2 else ''})")
    timings = {"update": [], "query": [], "frame": []}

    def query(points: np.ndarray):
        start = time.perf_counter()
        result = sphere.query(points, mode="adf", outputs=("distance", "normal"))
        timings["query"].append(time.perf_counter() - start)
        return result.distance, result.normal

    reports = []
    frame = 0
    while not stop.stopped and (args.frames is None or frame < args.frames):
        frame += 1
        with stop.frame():
            start = time.perf_counter()
            sphere.update(unit * motion.radius + motion.centre(cloth.time + settings.frame_time))
            update_s = time.perf_counter() - start
            report = cloth.step(query)
            if sheet is not None:
                sheet.stream(cloth.positions.astype(np.float32))
            timings["update"].append(update_s)
            timings["frame"].append(time.perf_counter() - start)
            reports.append(report)
        if stop.stopped:
            break
        _live(f"frame {frame:5d} | {1.0 / np.mean(timings['frame'][-30:]):5.1f} fps | sphere update "
              f"{1e3 * timings['update'][-1]:6.2f} ms | query {1e3 * timings['query'][-2]:6.2f} ms | contacts "
              f"{report.contacts:5d} | penetration {1e3 * report.penetration:6.2f} mm | kinetic "
              f"{report.kinetic_energy:7.3f} J")
        if not report.finite:
            print("\nbadf demo: the cloth state is not finite", file=sys.stderr)
            return 1
    print()
    if reports:
        print(f"summary: {len(reports)} frames, all finite, max penetration {1e3 * max(r.penetration for r in reports):.2f} mm, "
              f"max kinetic energy {max(r.kinetic_energy for r in reports):.3f} J, median sphere update "
              f"{1e3 * np.median(timings['update']):.2f} ms, median query ({len(cloth.positions)} points) "
              f"{1e3 * np.median(timings['query']):.2f} ms")
    return 0


def _live(line: str) -> None:
    """One live line: rewritten in place on a terminal, printed whole otherwise."""
    if sys.stdout.isatty():
        sys.stdout.write("\r" + line)
        sys.stdout.flush()
    else:
        print(line, flush=True)


if __name__ == "__main__":  # pragma: no cover
    multiprocessing.freeze_support()
