"""The web viewer: its colours and plane geometry against hand-made cases, its settings, its import boundary,
and the whole path in a real headless Chromium: a worker process, the viewer, the page, what it renders."""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import meshes
import numpy as np
import pytest
from conftest import free_endpoint, wait_until
from service_processes import worker_on

from badf.client import Client
from badf.protocol import CELL_EMPTY, CELL_LEAF
from badf.web_viewer import Viewer, ViewerSettings, viewer_process
from badf.web_viewer import _cli as viewer_cli
from badf.web_viewer._browser import HeadlessChromium, find_chromium, group_alive, slice_missing
from badf.web_viewer._colors import auto_scale, diverging_rgb, legend_html, level_rgb, round_up
from badf.web_viewer._plane import PlaneFrame, cell_outlines, leaf_corners, on_both_sides, zero_contour

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"


# --- colours -------------------------------------------------------------------------------------------


def test_colours_are_blue_inside_white_at_zero_red_outside() -> None:
    rgb = diverging_rgb(np.array([-2.0, -1.0, -0.3, 0.0, 0.3, 1.0, 2.0]), 1.0).astype(int)
    blue, red = rgb[:, 2] - rgb[:, 0], rgb[:, 0] - rgb[:, 2]
    assert (blue[:3] > 60).all() and (red[4:] > 60).all()
    assert (rgb[3] > 240).all()
    np.testing.assert_array_equal(rgb[0], rgb[1])  # saturated beyond the scale (and both on a band)
    assert rgb[1].sum() < rgb[2].sum()  # deeper is darker
    with pytest.raises(ValueError, match="scale"):
        diverging_rgb(np.zeros(3), 0.0)
    saturated_red = diverging_rgb(np.array([1.1]), 1.0)[0]  # off the bands
    np.testing.assert_array_equal(diverging_rgb(np.array([np.nan, np.inf]), 1.0), [(128, 128, 128), saturated_red])


def test_bands_mark_every_fifth_of_the_scale() -> None:
    on_band = np.array([0.205, 0.405, 0.605, 0.805, -0.405])
    shaded = diverging_rgb(on_band, 1.0).astype(int).sum(axis=1)
    past = diverging_rgb(on_band + np.sign(on_band) * 0.025, 1.0).astype(int).sum(axis=1)
    assert (shaded < past - 20).all()


def test_scales_round_up_and_show_both_sides() -> None:
    assert [round_up(x) for x in (0.0, 0.07, 0.1, 0.11, 0.3, 7.0)] == [1.0, 0.1, 0.1, 0.2, 0.5, 10.0]
    assert auto_scale(np.array([-0.04, 0.1])) == pytest.approx(0.05)  # the inside depth decides
    assert auto_scale(np.array([-0.01, 0.8])) == pytest.approx(0.2)  # a quarter of the outside
    assert auto_scale(np.array([np.nan])) == 1.0
    assert "\N{MINUS SIGN}0.2" in legend_html(0.2) and "+0.1" in legend_html(0.2)


def test_level_colours_are_grey() -> None:
    rgb = level_rgb(np.arange(8), 7).astype(int)
    assert (rgb[:, 0] == rgb[:, 2]).all() and (np.diff(rgb[:, 0]) > 0).all()


# --- the plane ---------------------------------------------------------------------------------------


def test_image_pose_puts_each_pixel_on_its_sample() -> None:
    """viser draws an image's column j along its local x and row i along its local y (row 0 at -y); the
    pose must carry that onto the plane so that pixel (i, j) lies where the slice sampled (i, j)."""
    from viser import transforms

    rows, cols = 4, 5
    for axis in ("x", "y", "z"):
        plane = PlaneFrame(axis, 0.3, ((-1.0, 2.0), (1.5, 4.0)))
        wxyz, centre, width, height = plane.image_pose()
        rotation = transforms.SO3(np.array(wxyz)).as_matrix()
        i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        local = np.stack([-width / 2 + (j + 0.5) * width / cols, -height / 2 + (i + 0.5) * height / rows,
                          np.zeros_like(i, dtype=float)], axis=-1)  # fmt: skip
        drawn = local @ rotation.T + centre
        u = -1.0 + (j + 0.5) * 2.5 / cols
        v = 2.0 + (i + 0.5) * 2.0 / rows
        np.testing.assert_allclose(drawn, plane.to_world(u, v), atol=1e-6, err_msg=axis)


def test_zero_contour_follows_a_circle() -> None:
    size, radius = 64, 0.6
    plane = PlaneFrame("y", -0.25, ((-1.0, -1.0), (1.0, 1.0)))
    centres = -1.0 + (np.arange(size) + 0.5) * 2.0 / size
    u, v = np.meshgrid(centres, centres)  # rows along v, columns along u
    grid = np.hypot(u - 0.1, v + 0.05) - radius
    segments = zero_contour(grid, plane)
    assert len(segments) > 100
    ends = segments.reshape(-1, 3)
    np.testing.assert_allclose(ends[:, 1], -0.25)  # on the plane; u = x, v = z for a y-plane
    cell = 2.0 / size
    assert np.abs(np.hypot(ends[:, 0] - 0.1, ends[:, 2] + 0.05) - radius).max() < 0.05 * cell
    length = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1).sum()
    assert length == pytest.approx(2 * np.pi * radius, rel=0.01)
    assert len(zero_contour(np.ones((8, 8)), plane)) == 0


def test_a_saddle_gives_two_segments() -> None:
    plane = PlaneFrame("z", 0.0, ((0.0, 0.0), (2.0, 2.0)))
    segments = zero_contour(np.array([[-1.0, 1.0], [1.0, -1.0]]), plane)
    assert segments.shape == (2, 2, 3)


def test_cell_outlines_lie_on_the_plane() -> None:
    plane = PlaneFrame("x", 0.5, ((-1.0, -1.0), (1.0, 1.0)))
    boxes = np.array([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.5]]], np.float32)
    outline = cell_outlines(boxes, plane)
    assert outline.shape == (4, 2, 3)
    np.testing.assert_allclose(outline[:, :, 0], 0.5)
    assert {tuple(p) for p in outline[:, 0, 1:].tolist()} == {(-1.0, 0.0), (0.0, 0.0), (0.0, 0.5), (-1.0, 0.5)}
    lifted = on_both_sides(outline, plane, 0.01)
    np.testing.assert_allclose(np.unique(lifted[:, :, 0]), [0.49, 0.51])


def test_leaf_corners_are_shared_once() -> None:
    boxes = np.array(
        [[[0, 0, 0], [1, 1, 1]], [[1, 0, 0], [2, 1, 1]], [[0, 0, 0], [2, 2, 2]]], np.float32
    )  # two leaves sharing a face, and their (refined) parent
    flags = np.array([CELL_LEAF, CELL_LEAF | CELL_EMPTY, 0], np.uint8)
    corners, probes = leaf_corners(boxes, flags)
    assert len(corners) == 12
    assert ((corners == 0) | (corners == 1) | (corners == 2)).all()
    inside_some_leaf = [
        any((probe > box[0]).all() and (probe < box[1]).all() for box in boxes[:2]) for probe in probes
    ]
    assert all(inside_some_leaf)
    assert np.abs(probes - corners).max() < 0.01


# --- settings, command line, import boundary -------------------------------------------------------


def test_settings_are_checked() -> None:
    for bad in ({"port": 70000}, {"resolution": 300}, {"up": "up"}, {"max_slice_hz": 0}, {"timeout_s": float("nan")},
                {"object_name": "a/b"}):  # fmt: skip
        with pytest.raises(ValueError):
            ViewerSettings(**bad)


def test_command_line_flags() -> None:
    parser = argparse.ArgumentParser()
    viewer_cli.add_arguments(parser)
    defaults = viewer_cli.settings_from(parser.parse_args([]))
    assert (defaults.connect, defaults.host, defaults.port) == ("tcp/127.0.0.1:7447", "127.0.0.1", 8080)
    given = viewer_cli.settings_from(parser.parse_args(["--connect", "tcp/10.0.0.2:7447", "--port", "9000",
                                                        "--host", "0.0.0.0", "--resolution", "128"]))  # fmt: skip
    assert (given.connect, given.port, given.host, given.resolution) == ("tcp/10.0.0.2:7447", 9000, "0.0.0.0", 128)


def test_command_line_errors_are_told(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    parser = argparse.ArgumentParser()
    viewer_cli.add_arguments(parser)
    unreachable = parser.parse_args(["--connect", free_endpoint(), "--timeout", "1", "--port", "0"])
    assert viewer_cli.run(unreachable) == 2
    assert "cannot reach a Zenoh router" in capsys.readouterr().err
    for host in ("192.0.2.1", "256.1.1.1"):  # not this machine's (a documentation address), and not an address
        elsewhere = parser.parse_args(["--connect", free_endpoint(), "--host", host, "--port", "0"])
        assert viewer_cli.run(elsewhere) == 2  # viser waited forever on these, deaf to Ctrl-C
        assert f"cannot serve the page on host '{host}'" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "viser", None)  # as if viser were not installed
    assert viewer_cli.run(unreachable) == 2
    assert "pip install 'badf[viewer]'" in capsys.readouterr().err


def test_the_viewer_never_imports_the_worker() -> None:
    code = (
        "import sys, badf.web_viewer, badf.web_viewer._cli, badf.web_viewer._viewer; "
        "bad = sorted(m for m in sys.modules if m.startswith('badf.server') or m.split('.')[0] == 'warp'); "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


# --- with a worker --------------------------------------------------------------------------------


def engine_queries(client: Client, name: str) -> int:
    """Field queries and slices the engine has answered for `name`, from the worker's snapshot."""
    stats = client.object(name).info().field_stats
    return int(stats.get("queries", 0)) + int(stats.get("slices", 0))


@pytest.fixture(scope="module")
def served():
    """A worker process with Spot registered and bent (frame 1); yields (endpoint, client, frames)."""
    endpoint = free_endpoint()
    vertices, faces = meshes.load("spot")
    frames = [vertices, bend(vertices, 0.15), bend(vertices, 0.3)]
    with worker_on(endpoint, worker_id="viewer-test") as _worker, Client(endpoint, timeout=60) as client:
        remote = client.register("spot", vertices, faces, depth=5)
        remote.update(frames[1])
        yield endpoint, client, frames


def bend(vertices: np.ndarray, amount: float) -> np.ndarray:
    """Spot bent sideways along its height: an object mid-deformation."""
    height = (vertices[:, 1] - vertices[:, 1].min()) / np.ptp(vertices[:, 1])
    bent = vertices.copy()
    bent[:, 0] += amount * height**2
    return bent


def test_corner_probes_read_the_corners_own_samples(served) -> None:
    """The viewer colours each leaf corner by the field at a probe just inside its leaf; that must be the
    corner's sample, which the engine computed as the exact distance there."""
    _, client, _ = served
    remote = client.object("spot")
    cut = remote.slice("z", 0.1, resolution=16)
    corners, probes = leaf_corners(cut.cell_boxes, cut.cell_flags)
    assert len(corners) > 100
    sampled = remote.query(probes, mode="adf").distance
    exact = remote.query(corners, mode="exact").distance
    largest_leaf = float((cut.cell_boxes[:, 1] - cut.cell_boxes[:, 0]).max())
    np.testing.assert_allclose(sampled, exact, rtol=0, atol=2e-3 * largest_leaf)  # the probe's offset, 1-Lipschitz


def test_the_viewer_switches_objects_and_outlives_a_deletion(served) -> None:
    endpoint, client, _ = served
    client.register("ball", *meshes.load("sphere"), depth=4)
    try:
        with Viewer(ViewerSettings(connect=endpoint, port=0, watch_without_browser=True)) as viewer:
            wait_until(lambda: viewer.status().objects == ("ball", "spot"), timeout=60, what="both objects listed")
            wait_until(lambda: shows(viewer, "ball"), timeout=60, what="a slice of the first object by name")
            viewer.set_view(object_name="spot", axis="x", corners=True)
            wait_until(lambda: shows(viewer, "spot") and viewer.status().corner_points > 0, timeout=60,
                       what="a slice of spot with its corner samples")  # fmt: skip
            assert viewer.status().slice_axis == "x"
            viewer.set_view(object_name="ball")
            wait_until(lambda: shows(viewer, "ball"), timeout=60, what="the ball again")
            client.object("ball").delete()
            wait_until(lambda: shows(viewer, "spot"), timeout=60, what="the viewer falling back to spot")
            wait_until(lambda: viewer.status().problem is None, timeout=60, what="the problem to clear")
    finally:
        if "ball" in [info.name for info in client.objects()]:
            client.object("ball").delete()


def test_the_viewer_reopens_an_object_registered_again_with_the_same_counts(served) -> None:
    """A replace with as many vertices and faces kept the old faces and depth on the page (the viewer
    compared counts); it now reopens on any new registration, even one numbered below the frames seen."""
    endpoint, client, _ = served
    vertices, faces = meshes.load("sphere")
    client.register("ball", vertices, faces, depth=4)
    try:
        settings = ViewerSettings(connect=endpoint, port=0, watch_without_browser=True, object_name="ball")
        with Viewer(settings) as viewer:
            wait_until(lambda: shows(viewer, "ball") and viewer.status().depth == 4, timeout=60, what="the ball")
            client.register("ball", vertices[::-1].copy(), (len(vertices) - 1 - faces)[:, ::-1].copy(), depth=6,
                            replace=True)  # the same triangles, the vertices numbered the other way
            wait_until(lambda: viewer.status().depth == 6 and shows(viewer, "ball"), timeout=60,
                       what="the ball at its new depth")  # fmt: skip
    finally:
        if "ball" in [info.name for info in client.objects()]:
            client.object("ball").delete()


def test_the_viewer_follows_an_object_to_the_worker_it_moves_to() -> None:
    """The shown object's worker leaves and a client registers the object again on another worker: the viewer
    used to keep its handle on the gone worker, showing ObjectUnavailableError until another object was picked."""
    from test_worker_plumbing import FACES, VERTICES, ThreadWorker

    endpoint = free_endpoint()
    with ThreadWorker(endpoint, worker_id="stays"), Client(endpoint, timeout=10) as client:
        leaving: ThreadWorker | None = ThreadWorker("", worker_id="leaves", connect=(endpoint,)).__enter__()
        try:
            wait_until(lambda: len(client.workers()) == 2, what="both workers")
            client.register("anchor", VERTICES, FACES, worker="stays")
            mover = client.register("mover", VERTICES[:30], FACES[:2], worker="leaves")
            settings = ViewerSettings(connect=endpoint, port=0, watch_without_browser=True, object_name="mover")
            with Viewer(settings) as viewer:
                wait_until(lambda: shows(viewer, "mover"), timeout=60, what="a slice of the mover")
                leaving.__exit__(None, None, None)
                leaving = None
                wait_until(lambda: "Unavailable" in (viewer.status().problem or ""), timeout=60,
                           what="the viewer to see the mover's worker go")  # fmt: skip
                mover.reregister()
                assert mover.worker == "stays"
                wait_until(lambda: shows(viewer, "mover"), timeout=60, what="the mover again, on its new worker")
        finally:
            if leaving is not None:
                leaving.__exit__(None, None, None)


def shows(viewer: Viewer, name: str) -> bool:
    status = viewer.status()
    return status.object_name == name and status.slice_frame is not None and status.problem is None


def test_badf_view_serves_the_page_and_stops_on_sigint(served) -> None:
    endpoint, _, _ = served
    port = free_port()
    code = f"from badf.cli import main; raise SystemExit(main(['view', '--connect', '{endpoint}', '--port', '{port}']))"
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True)
    said: list[str] = []  # stderr, read as it comes: the page answers while the viewer still starts, before
    reader = threading.Thread(target=lambda: said.extend(process.stderr), daemon=True)  # it says "open"
    reader.start()
    try:
        wait_until(lambda: (page_answers(port) and any("badf view: open" in line for line in said))
                   or process.poll() is not None, timeout=120, what="the page and the viewer's 'open' line")
        assert process.poll() is None, "".join(said)
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=60) == 0
        reader.join(30)
        assert f"open http://127.0.0.1:{port}/" in "".join(said)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=30)


def test_viewer_process_in_a_script_without_the_main_guard_says_so(tmp_path) -> None:
    """docs/viewer.md's viewer_process example, run as a plain script, failed: the spawned child imports the
    script again and may not start a process there, and the parent said only "exited with status 1 before
    serving" (eleventh outside check). It now names the missing `if __name__ == "__main__":` guard."""
    script = tmp_path / "view_it.py"
    script.write_text("from badf.web_viewer import viewer_process\n\n"
                      f"with viewer_process(connect={free_endpoint()!r}, port=0, start_timeout_s=60) as url:\n"
                      "    print(url)\n")
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert done.returncode == 1, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("RuntimeError: the viewer process exited with status 1 while starting"), done.stderr
    assert 'calls viewer_process needs `if __name__ == "__main__":` around the call' in last

def test_viewer_process_serves_until_the_block_ends(served) -> None:
    endpoint, _, _ = served
    port = free_port()
    with viewer_process(connect=endpoint, port=port) as url:
        assert url == f"http://127.0.0.1:{port}/"
        wait_until(lambda: page_answers(port), timeout=60, what="the page")
    assert not page_answers(port)
    with pytest.raises(RuntimeError, match="exited"):
        with viewer_process(connect=free_endpoint(), port=0, timeout_s=1):
            pass  # no router there: the child cannot start


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def page_answers(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as response:
            return response.status == 200
    except OSError:
        return False


def observe_for(seconds: float) -> None:
    """Let `seconds` pass: a window in which something that must not happen would have happened."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.05)


def test_nothing_is_asked_while_no_browser_looks(served) -> None:
    endpoint, client, _ = served
    before = engine_queries(client, "spot")
    with Viewer(ViewerSettings(connect=endpoint, port=0, max_info_hz=50)) as viewer:
        observe_for(1.5)
        status = viewer.status()
        assert (status.requests, status.slices_drawn, status.object_name, status.watching) == (0, 0, None, False)
    assert engine_queries(client, "spot") == before


@pytest.mark.skipif(find_chromium() is None, reason="no Chromium on PATH: ./dev test installs Debian's chromium")
def test_the_page_shows_the_slice_in_a_real_browser(served) -> None:
    endpoint, client, frames = served
    remote = client.object("spot")
    ARTIFACTS.mkdir(exist_ok=True)
    with Viewer(ViewerSettings(connect=endpoint, port=0)) as viewer:
        with HeadlessChromium(viewer.url, width=1280, height=800) as browser:
            group = browser.process.pid
            wait_until(lambda: len(viewer.server.get_clients()) == 1, timeout=120, what="the page to connect")
            wait_until(lambda: viewer.status().slice_frame == 1, timeout=120, what="a slice of frame 1")
            wait_until(lambda: viewer.status().mesh_frame == 1, timeout=60, what="the mesh of frame 1")
            status = viewer.status()
            assert (status.object_name, status.objects, status.problem) == ("spot", ("spot",), None)
            [page] = viewer.server.get_clients().values()
            (ARTIFACTS / "viewer-page.png").write_bytes(browser.screenshot())  # the whole window, panel too
            viewer.set_view(mesh=False)  # the opaque mesh hides the slice's inside, as it should
            render_until_drawn(page, ARTIFACTS / "viewer-render.png", timeout=300)
            viewer.set_view(mesh=True)
            remote.update(frames[2])  # the page follows the object
            wait_until(lambda: viewer.status().slice_frame == 2, timeout=120, what="a slice of frame 2")
            wait_until(lambda: viewer.status().mesh_frame == 2, timeout=60, what="the mesh of frame 2")
        assert not group_alive(group), "Chromium's process group outlived the test"
        wait_until(lambda: not viewer.status().watching, timeout=60, what="the viewer to see the page gone")
        asked = viewer.status().requests
        observe_for(1.5)  # the browser is gone: the viewer asks the workers nothing more
        assert viewer.status().requests == asked


def render_until_drawn(page, path: Path, *, timeout: float) -> None:
    """Ask the page for renders until one shows the slice (the browser decodes the slice's image on its own
    time), keeping the last one at `path`; fail with what is missing when `timeout` seconds pass first."""
    deadline = time.monotonic() + timeout
    while True:
        image = page.get_render(600, 800, transport_format="png", timeout=timeout)
        save_png(path, image)
        missing = slice_missing(image)
        if not missing:
            return
        if time.monotonic() > deadline:
            pytest.fail(f"the page's render (kept at {path}) lacks: {'; '.join(missing.values())}")


def test_a_blank_render_is_told_apart() -> None:
    """The check the browser test relies on fails for a blank canvas and for one sign only."""
    assert set(slice_missing(np.full((60, 80, 3), 255, np.uint8))) == {"inside", "outside", "contour", "colours"}
    one_sign = np.zeros((60, 80, 3), np.uint8)
    one_sign[:30] = (200, 60, 50)
    one_sign[30:] = (250, 250, 250)
    assert set(slice_missing(one_sign)) == {"inside", "contour"}


def save_png(path: Path, image: np.ndarray) -> None:
    import imageio.v3 as iio

    iio.imwrite(path, image)
