"""Viewer benchmark: how fast a slice of an object gets from the worker onto the viewer's page.

    python -m badf.bench.viewer --mesh PATH.npz [--device cuda:0] [--resolution 256] [--small] [--out R.json]
                                [--screenshot PAGE.png]

With a worker on the device (its own process, loopback TCP) holding the mesh, it times
  * through the client, each request the viewer makes: a slice with its octree cells (what the viewer asks
    by default), a slice without cells, an info poll, a mesh poll (vertices only), and a new frame followed
    by a slice (what following a deforming object costs per picture);
  * in this process, the viewer's own work on a slice reply: decoding it, colouring the grid, the zero
    contour, the cell outlines, and the image update in viser (JPEG encoding);
  * end to end through a running Viewer (no browser needed: viser queues what it would send): the slider
    set to a new position until the new slice is drawn (rate limits lifted), and the slices drawn per
    second while another process streams frames (at the viewer's default rate limits, and lifted).
Each figure is the median (and p99) after 3 warm-up calls, measured at the caller: what the viewer waits,
Python included. The slice plane sweeps the middle of the object along z. A mesh with a sequence of frames
(T, N, 3) streams those; a single mesh streams a smooth deformation of itself. `--screenshot` opens the
page in a headless Chromium while frames stream and writes what the browser window shows.
"""

from __future__ import annotations

import argparse
import itertools
import json
import multiprocessing
import platform
import socket
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Callable, Iterator

import numpy as np

from badf.bench._common import bench_device_name, deform, fill_sized_defaults, print_table, start_warp, timestamp
from badf.server._mesh_files import MESH_HELP, read_frames

_SPAWN = multiprocessing.get_context("spawn")
_WARM_UP = 3
_FULL = {"repeats": 100, "follow_s": 10.0}
_SMALL = {"repeats": 12, "follow_s": 4.0}
_NAME = "viewed"


@dataclass
class Timing:
    what: str
    samples: int
    median_ms: float
    p99_ms: float
    per_second: float  # 1 / median
    reply_bytes: int = 0


@dataclass
class Following:
    """The viewer following a stream of frames for `seconds`."""

    what: str
    seconds: float
    frames_streamed: int
    slices_drawn: int
    slices_per_second: float
    frames_advanced: int  # newest frame drawn at the end, less the one at the start
    round_trip_ms: float | None  # the viewer's own medians over the slices drawn in the window
    draw_ms: float | None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mesh", required=True, help=MESH_HELP)
    parser.add_argument("--device", default=None, help="cpu, cuda:0, ... (default: the first GPU, else cpu)")
    parser.add_argument("--depth", type=int, default=7, help="octree depth (default 7)")
    parser.add_argument("--resolution", type=int, default=256, help="slice grid per side (default 256)")
    parser.add_argument("--small", action="store_true", help="CPU-sized defaults for the two flags below")
    parser.add_argument("--repeats", type=int, help="timed calls per row (100; small: 12)")
    parser.add_argument("--follow-s", type=float, help="seconds of following a stream, per rate limit (10; small: 4)")
    parser.add_argument("--stream-fps", type=float, default=60.0, help="frames per second streamed (default 60)")
    parser.add_argument("--axis", default="z", choices=("x", "y", "z"), help="slice axis (default z)")
    parser.add_argument("--screenshot", default=None, metavar="PNG", help="also write the page as a browser shows it")
    parser.add_argument("--out", default=None, help="write the full results as JSON here")


def run(args: argparse.Namespace) -> int:
    device = start_warp(args.device)
    fill_sized_defaults(args, _SMALL, _FULL)
    frames, faces = _load_frames(args.mesh)
    report = {
        "benchmark": "viewer",
        "date": timestamp(),
        "device": bench_device_name(device),
        "host": platform.node(),
        "mesh": {"path": args.mesh, "vertices": frames.shape[1], "faces": len(faces), "frames": len(frames)},
        "depth": args.depth,
        "resolution": args.resolution,
        "axis": args.axis,
    }
    viser_missing = _viser_missing()
    with _worker(device) as endpoint:
        from badf.client import Client

        with Client(endpoint, timeout=120) as client:
            remote = client.register(_NAME, frames[0], faces, depth=args.depth)
            positions = _sweep(frames[0], "xyz".index(args.axis), args.repeats)
            timings = _client_timings(remote, frames, positions, args)
            timings += _viewer_side_timings(remote, positions, args, viser_missing)
            report["accuracy"] = _slice_accuracy(remote, frames[0], faces, float(positions[len(positions) // 4]), args)
            report["worker_field_stats"] = remote.info().field_stats
            following: list[Following] = []
            if viser_missing is None:
                steps, following = _end_to_end(endpoint, frames, positions, args)
                timings.append(steps)
    report["timings"] = [asdict(t) for t in timings]
    report["following"] = [asdict(f) for f in following]
    title = (
        f"viewer on {report['device']}, {args.mesh} ({len(faces)} triangles), depth {args.depth}, "
        f"{args.resolution}x{args.resolution} {args.axis}-slices"
    )
    print_table(
        title,
        ["what", "n", "median ms", "p99 ms", "per s", "reply MB"],
        [[t.what, t.samples, round(t.median_ms, 3), round(t.p99_ms, 3), round(t.per_second, 1),
          round(t.reply_bytes / 1e6, 3)] for t in timings],
    )  # fmt: skip
    if following:
        print_table(
            f"the viewer following frames streamed at {args.stream_fps:g} fps (its own medians)",
            ["limits", "s", "frames sent", "slices drawn", "slices/s", "frames advanced", "round trip ms", "draw ms"],
            [[f.what, round(f.seconds, 1), f.frames_streamed, f.slices_drawn, round(f.slices_per_second, 1),
              f.frames_advanced, _round(f.round_trip_ms), _round(f.draw_ms)] for f in following],
        )  # fmt: skip
    accuracy = report["accuracy"]
    print(f"the slices' accuracy: {accuracy['points']} samples of one slice against the float64 oracle: "
          f"{accuracy['max_error_diag']:.2e} / {accuracy['mean_error_diag']:.2e} diagonals (max / mean)")
    if viser_missing is not None:
        print(f"\nviewer rows skipped: {viser_missing}")
        report["skipped"] = viser_missing
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(report, handle, indent=2)
        print("wrote", args.out)
    return 0


def _slice_accuracy(remote, vertices: np.ndarray, faces: np.ndarray, position: float, args) -> dict:
    """What the timed slices are worth: samples of one slice of `vertices` (the field's values at the grid's
    sample points, as SliceReply places them) against the float64 oracle."""
    from badf.bench._oracle import ORACLE_SAMPLE, errors_against, signed_distance

    remote.update(vertices)
    reply = remote.slice(args.axis, position, resolution=args.resolution)
    rows, columns = reply.grid.shape
    picked = np.random.default_rng(0).choice(rows * columns, size=min(ORACLE_SAMPLE, rows * columns), replace=False)
    row, column = np.divmod(picked, columns)
    (u_min, v_min), (u_max, v_max) = reply.extent
    points = np.empty((len(picked), 3))
    axis = "xyz".index(reply.axis)
    u_axis, v_axis = [other for other in range(3) if other != axis]
    points[:, axis] = reply.position
    points[:, u_axis] = u_min + (column + 0.5) * (u_max - u_min) / columns
    points[:, v_axis] = v_min + (row + 0.5) * (v_max - v_min) / rows
    return errors_against(reply.grid[row, column], signed_distance(points, vertices, faces), vertices)


def _round(value: float | None) -> float | str:
    return "-" if value is None else round(value, 2)


def _load_frames(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(T, N, 3) float32 frames and (M, 3) int32 faces: a sequence's own frames, or 32 frames of a smooth
    deformation of a single mesh."""
    frames, faces = read_frames(path)
    if len(frames) == 1:
        frames = np.stack([deform(frames[0], k / 32) for k in range(32)])
    return np.ascontiguousarray(frames), faces


def _slider(vertices: np.ndarray, axis: int, count: int) -> np.ndarray:
    """Plane positions across the middle 80% of the object and back, as a dragged slider goes, for `count` calls:
    repeated end to end, no two in a row are the same, the last and the first included."""
    low, high = float(vertices[:, axis].min()), float(vertices[:, axis].max())
    there = np.linspace(low + 0.1 * (high - low), high - 0.1 * (high - low), max(3, (count + 1) // 2))
    return np.concatenate([there, there[-2:0:-1]])


def _sweep(vertices: np.ndarray, axis: int, count: int) -> np.ndarray:
    """`count` plane positions along the slider's way (`_slider`); no two in a row are the same."""
    return np.resize(_slider(vertices, axis, count), count)


def _timed(what: str, work: Callable[[int], object], count: int, *, reply_bytes: int = 0) -> Timing:
    for warm in range(_WARM_UP):
        work(warm)
    samples = np.empty(count)
    for index in range(count):
        begin = time.perf_counter()
        work(index)
        samples[index] = time.perf_counter() - begin
    median = float(np.median(samples))
    return Timing(what, count, median * 1e3, float(np.percentile(samples, 99) * 1e3), 1.0 / median, reply_bytes)


def _client_timings(remote, frames: np.ndarray, positions: np.ndarray, args) -> list[Timing]:
    """The viewer's requests, one at a time through the client, as the viewer makes them."""
    from badf.protocol import encode

    axis, resolution, n = args.axis, args.resolution, args.repeats
    levels = (0, args.depth)

    def cut(i: int, cells: bool = True):
        return remote.slice(axis, float(positions[i % n]), resolution=resolution, levels=levels, cells=cells)

    def frame_then_slice(i: int) -> None:
        remote.update(frames[(i + 1) % len(frames)])
        cut(i)

    with_cells, grid_only = len(encode(cut(0))), len(encode(cut(0, cells=False)))
    mesh_bytes = len(encode(remote.mesh(faces=False)))
    label = f"{resolution}x{resolution}"
    return [
        _timed(f"slice {label} + cells (the viewer's request)", cut, n, reply_bytes=with_cells),
        _timed(f"slice {label}, grid only", lambda i: cut(i, cells=False), n, reply_bytes=grid_only),
        _timed("info poll", lambda _i: remote.info(), n),
        _timed("mesh poll (vertices)", lambda _i: remote.mesh(faces=False), n, reply_bytes=mesh_bytes),
        _timed(f"new frame (update) + slice {label} + cells", frame_then_slice, n),
    ]


def _viewer_side_timings(remote, positions: np.ndarray, args, viser_missing: str | None) -> list[Timing]:
    """The viewer's own work on one slice reply, in this process."""
    from badf.protocol import SliceReply, decode, encode
    from badf.web_viewer._colors import auto_scale, diverging_rgb
    from badf.web_viewer._plane import PlaneFrame, cell_outlines, on_both_sides, zero_contour

    reply = remote.slice(args.axis, float(positions[len(positions) // 4]), resolution=args.resolution,
                         levels=(0, args.depth))  # fmt: skip
    wire = bytes(encode(reply))
    plane = PlaneFrame(reply.axis, reply.position, reply.extent)
    scale = auto_scale(reply.grid)
    image = diverging_rgb(reply.grid, scale)
    n = args.repeats
    timings = [
        _timed("viewer: decode the slice reply", lambda _i: decode(wire, SliceReply), n),
        _timed("viewer: colour the grid", lambda _i: diverging_rgb(reply.grid, auto_scale(reply.grid)), n),
        _timed("viewer: zero contour", lambda _i: zero_contour(reply.grid, plane), n),
        _timed(f"viewer: outlines of {len(reply.cell_boxes)} cells",
               lambda _i: on_both_sides(cell_outlines(reply.cell_boxes, plane), plane, 1e-3), n),  # fmt: skip
    ]
    if viser_missing is None:
        import viser

        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        try:
            handle = server.scene.add_image("/image", image, 1.0, 1.0, format="jpeg", jpeg_quality=95)
            flipped = [image, np.ascontiguousarray(image[::-1])]  # a different picture each time

            def update(i: int) -> None:
                handle.image = flipped[i % 2]

            timings.append(_timed("viewer: image update in viser (JPEG)", update, n))
        finally:
            server.stop()
    return timings


def _end_to_end(endpoint: str, frames: np.ndarray, positions: np.ndarray, args) -> tuple[Timing, list[Following]]:
    """A running Viewer: slider steps until drawn, and following a stream at default and lifted limits."""
    from badf.web_viewer import Viewer, ViewerSettings

    base = ViewerSettings(connect=endpoint, port=0, resolution=args.resolution, watch_without_browser=True)
    lifted = ViewerSettings(connect=endpoint, port=0, resolution=args.resolution, watch_without_browser=True,
                            max_slice_hz=1000.0, max_info_hz=1000.0, max_mesh_hz=1000.0)  # fmt: skip
    n = len(positions)
    # every call moves the slider on, the warm-up's included: a call to where it already is would draw nothing
    slider, moves = _slider(frames[0], "xyz".index(args.axis), n), itertools.count()
    with Viewer(lifted) as viewer:
        _wait(lambda: viewer.status().slices_drawn > 0, 300, "the viewer's first slice")
        viewer.set_view(axis=args.axis)

        def step(_: int) -> None:
            drawn, position = viewer.status().slices_drawn, float(slider[next(moves) % len(slider)])
            viewer.set_view(position=position)
            _wait(lambda: viewer.status().slices_drawn > drawn and viewer.status().slice_position == position,
                  120, "a slice at the new position")  # fmt: skip

        steps = _timed("viewer end to end: slider moved, new slice drawn (no rate limit)", step, n)
        following = [_follow(viewer, "lifted (1000/s)", frames, endpoint, args)]
    with Viewer(base) as viewer:
        _wait(lambda: viewer.status().slices_drawn > 0, 300, "the viewer's first slice")
        viewer.set_view(axis=args.axis)
        following.insert(0, _follow(viewer, "defaults (slices <= 20/s)", frames, endpoint, args))
        if args.screenshot:
            _screenshot(viewer, frames, endpoint, args)
    return steps, following


def _follow(viewer, what: str, frames: np.ndarray, endpoint: str, args) -> Following:
    stop, sent = _SPAWN.Event(), _SPAWN.Value("i", 0)
    streamer = _SPAWN.Process(target=_stream, args=(endpoint, frames, args.stream_fps, stop, sent), daemon=True)
    streamer.start()
    try:
        _wait(lambda: sent.value > 0, 120, "the first streamed frame")
        first = viewer.status()
        started = time.monotonic()
        time.sleep(args.follow_s)  # the measurement window
        last, seconds = viewer.status(), time.monotonic() - started
    finally:
        stop.set()
        streamer.join(30)
        if streamer.is_alive():
            streamer.kill()
            streamer.join(30)
    drawn = last.slices_drawn - first.slices_drawn
    window = last.recent_slices_ms[len(last.recent_slices_ms) - min(drawn, len(last.recent_slices_ms)):]
    return Following(
        what=what,
        seconds=seconds,
        frames_streamed=sent.value,
        slices_drawn=drawn,
        slices_per_second=drawn / seconds,
        frames_advanced=(last.slice_frame or 0) - (first.slice_frame or 0),
        round_trip_ms=float(np.median([t[0] for t in window])) if window else None,
        draw_ms=float(np.median([t[1] for t in window])) if window else None,
    )


def _stream(endpoint: str, frames: np.ndarray, fps: float, stop, sent) -> None:
    """A client process streaming `frames` round and round at `fps` until `stop` (at most 10 minutes)."""
    from badf.client import Client

    with Client(endpoint, timeout=60) as client:
        remote = client.object(_NAME)
        begin = time.monotonic()
        count = 0
        while not stop.is_set() and time.monotonic() - begin < 600:
            remote.stream(frames[count % len(frames)])
            count += 1
            sent.value = count
            pause = begin + count / fps - time.monotonic()
            if pause > 0:
                stop.wait(pause)  # pacing the load, not synchronisation


def _screenshot(viewer, frames: np.ndarray, endpoint: str, args) -> None:
    """The page in a headless Chromium, mid-deformation: frames stream for a few seconds and stop; once the
    page shows the slice of the last frame, the whole window is captured. (While frames stream, a browser
    drawing in software decodes slice images more slowly than they come, so it would show an older image
    under newer lines.)"""
    from badf.web_viewer._browser import HeadlessChromium, slice_missing

    with HeadlessChromium(viewer.url, width=1600, height=1000) as browser:
        _wait(lambda: len(viewer.server.get_clients()) == 1, 120, "the page to connect")
        stop, sent = _SPAWN.Event(), _SPAWN.Value("i", 0)
        streamer = _SPAWN.Process(target=_stream, args=(endpoint, frames, args.stream_fps, stop, sent), daemon=True)
        streamer.start()
        try:
            _wait(lambda: (viewer.status().slice_frame or 0) > 3, 300, "slices of streamed frames")
            time.sleep(3.0)  # the object moves for a while
        finally:
            stop.set()
            streamer.join(30)
        _wait(lambda: _caught_up(viewer.status()), 300, "the slice and mesh of the last frame")
        [page] = viewer.server.get_clients().values()
        deadline = time.monotonic() + 300
        while {"outside", "contour"} & set(slice_missing(page.get_render(450, 600, timeout=300))):
            if time.monotonic() > deadline:
                raise SystemExit("badf bench viewer: the page never showed the slice")
        # Close the page's notice that WebGL runs in software (true of headless Chromium, not the viewer).
        browser.evaluate("document.querySelectorAll('.mantine-Notification-closeButton').forEach(b => b.click())")
        time.sleep(1.0)  # the notice fades out
        with open(args.screenshot, "wb") as handle:
            handle.write(browser.screenshot())
    print("wrote", args.screenshot, "at frame", viewer.status().slice_frame)


def _caught_up(status) -> bool:
    return status.slice_frame == status.mesh_frame == status.known_frame


def _wait(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit(f"badf bench viewer: gave up waiting for {what} after {timeout_s:g} s")
        time.sleep(0.001)


def _viser_missing() -> str | None:
    try:
        import viser  # noqa: F401
    except ImportError as error:
        return f"viser is not installed ({error}): pip install 'badf[viewer]'"
    return None


@contextmanager
def _worker(device: str) -> Iterator[str]:
    """A worker process on a free loopback port for the duration of the block; yields its endpoint."""
    from badf.server import WorkerSettings, worker_process

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{probe.getsockname()[1]}"
    settings = WorkerSettings(worker_id="bench", listen=(endpoint,), device=device, stats_interval_s=3600.0)
    with worker_process(settings, start_timeout_s=600.0):
        yield endpoint


def main() -> int:
    from badf.bench._cli import main_of

    return main_of("viewer")


if __name__ == "__main__":
    raise SystemExit(main())
