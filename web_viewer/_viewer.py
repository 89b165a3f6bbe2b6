"""The viewer process: a viser web page over the objects of the badf workers, fed over Zenoh only.

One refresh thread does all the work. It polls the chosen object's info (frame, counts, times), fetches
the object's newest vertices when its frame moved, asks for a slice when the plane or the frame changed,
and updates the scene. It sends one request at a time and waits for the answer, so requests never pile
up; each kind of request has a highest rate (ViewerSettings), and whatever changed in the meantime (frames
streamed, a slider dragged) is read afresh at the next turn, so intermediate states are skipped, never
queued. GUI callbacks only record and wake. Nothing is asked of the workers while no browser is connected.
viser keeps, per scene node, only the newest update that a browser has not received yet, so a slow
browser slows neither this process nor the workers.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from badf.client import Client, RemoteObject
from badf.client._client import timeout_seconds
from badf.protocol import (
    AXES,
    DEFAULT_ENDPOINT,
    BadfError,
    KeySpace,
    ObjectInfo,
    ObjectNotFoundError,
    ObjectUnavailableError,
    SliceReply,
    WorkerBusyError,
    check_name,
    zenoh_config,
)
from badf.web_viewer._colors import (
    ZERO_CONTOUR_RGB,
    auto_scale,
    diverging_rgb,
    format_distance,
    legend_html,
    level_rgb,
)
from badf.web_viewer._plane import PlaneFrame, cell_outlines, leaf_corners, on_both_sides, zero_contour

log = logging.getLogger("badf.web_viewer")

UpDirection = Literal["+x", "+y", "+z", "-x", "-y", "-z"]
UP_DIRECTIONS: tuple[str, ...] = ("+x", "+y", "+z", "-x", "-y", "-z")
RESOLUTIONS = (64, 128, 256, 512, 1024)
NO_OBJECT = "(no objects)"
MESH_RGB = (200, 200, 200)
# How often the list of objects is read again, and how often the panel's text may change.
_LISTING_PERIOD_S = 2.0
_PANEL_PERIOD_S = 0.25
# After an error (no worker, a timeout), wait this long before asking again.
_RETRY_PERIOD_S = 1.0
# Corner sample points beyond this many are neither asked for nor drawn.
MAX_CORNER_POINTS = 200_000
# The slice travels to the browser as a JPEG: at 256 x 256 it encodes in under 1 ms where PNG takes 16-30 ms
# (the contour is drawn as lines, so the image needs no sharp edges).
_JPEG_QUALITY = 95
# Overlays on the plane (contour, cell outlines) float this fraction of the domain off it, to either side.
_LIFT = 1e-3


def _import_viser() -> Any:
    try:
        import viser
    except ImportError as error:
        raise ImportError(
            f"the badf viewer needs viser, which is not installed ({error}); "
            "install it with: pip install 'badf[viewer]'"
        ) from None
    return viser


@dataclass(frozen=True)
class ViewerSettings:
    """What `badf view` takes. Rates are upper bounds in requests per second; `timeout_s` bounds each
    request to a worker; `port` 0 picks a free one (viser also moves to the next port when one is taken:
    read `Viewer.port`). `watch_without_browser` keeps refreshing with no browser connected, for benchmarks;
    otherwise nothing is asked of the workers while nobody looks."""

    connect: str = DEFAULT_ENDPOINT
    namespace: str = "badf"
    config_file: str | None = None
    host: str = "127.0.0.1"
    port: int = 8080
    object_name: str | None = None
    resolution: int = 256
    up: UpDirection = "+y"
    max_slice_hz: float = 20.0
    max_mesh_hz: float = 10.0
    max_info_hz: float = 20.0
    timeout_s: float = 10.0
    watch_without_browser: bool = False

    def __post_init__(self) -> None:
        check_port(self.port, "port")
        if self.resolution not in RESOLUTIONS:
            raise ValueError(f"resolution must be one of {', '.join(map(str, RESOLUTIONS))}, got {self.resolution!r}")
        if self.up not in UP_DIRECTIONS:
            raise ValueError(f"up must be one of {', '.join(UP_DIRECTIONS)}, got {self.up!r}")
        for name in ("max_slice_hz", "max_mesh_hz", "max_info_hz"):
            check_rate(getattr(self, name), name)
        timeout_seconds(self.timeout_s)  # as the client takes it, so a bad one is told before connecting
        KeySpace(self.namespace)
        if self.object_name is not None:
            check_name(self.object_name)
        connect = [self.connect] if isinstance(self.connect, str) else list(self.connect)
        zenoh_config(mode="client", connect=connect, config_file=self.config_file)  # names a malformed endpoint


def check_port(port: object, name: str) -> None:
    """ValueError, naming the port as `name` (a field or a flag), unless it is an integer in 0..65535."""
    if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
        raise ValueError(f"{name} must be an integer in 0..65535, got {port!r}")


# Rates the viewer's polls take, per second: below, a poll a few minutes apart reads as a viewer that hangs; above,
# the waits are shorter than one request's round trip, so the rate no longer limits anything (1e300 was taken)
MIN_RATE_HZ, MAX_RATE_HZ = 0.01, 1000.0


def check_rate(value: object, name: str) -> None:
    """ValueError, naming the rate as `name` (a field or a flag), unless it is a number in MIN_RATE_HZ..MAX_RATE_HZ."""
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (is_number and math.isfinite(value) and MIN_RATE_HZ <= value <= MAX_RATE_HZ):
        raise ValueError(f"{name} must be a finite positive number in {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} per second, "
                         f"got {value!r}")


@dataclass(frozen=True)
class SliceView:
    """What the user asks to see of the slice: the plane, the grid, which cells, and the colour scale
    (None: chosen from the slice)."""

    axis: str
    position: float
    resolution: int
    levels: tuple[int, int]
    cells: bool
    corners: bool
    scale: float | None


@dataclass(frozen=True)
class ViewerStatus:
    """A snapshot of what the page shows and how fast it follows (for tests, benchmarks and scripts).
    Times are medians over the last 50 slices; `slices_per_s` counts those drawn in the last 2 s."""

    object_name: str | None
    objects: tuple[str, ...]
    depth: int | None  # the shown object's octree depth (the levels slider's range)
    known_frame: int  # the newest frame of the object heard of
    slice_frame: int | None
    slice_axis: str | None
    slice_position: float | None
    corner_points: int  # corner samples drawn with the last slice
    mesh_frame: int | None
    slices_drawn: int
    meshes_drawn: int
    requests: int  # requests sent to the workers so far
    watching: bool  # False once the refresh thread has found no browser connected, and rests
    round_trip_ms: float | None  # asking for a slice until its reply is decoded
    draw_ms: float | None  # colouring, contour, cells and handing the scene to viser
    slices_per_s: float
    recent_slices_ms: tuple[tuple[float, float], ...]  # (round trip, draw) of the last 50 slices, newest last
    scale: float | None
    problem: str | None


@dataclass
class _Shown:
    """The object on screen and what was last drawn of it (the refresh thread's own)."""

    remote: RemoteObject
    info: ObjectInfo
    centre: np.ndarray  # the octree domain: a cube of side `side` around `centre`
    side: float
    depth: int
    faces: np.ndarray
    mesh_frame: int
    box_centre: np.ndarray  # the middle of the bounding box of the first vertices seen
    slice_view: SliceView | None = None
    slice_frame: int | None = None
    corner_points: int = 0
    scale: float | None = None


def check_host(host: str) -> None:
    """ValueError unless a socket can listen on `host` (an address of this machine, or a name for one). viser
    tries a thousand ports on an address it cannot bind, then waits forever for a server that never started
    (and Ctrl-C cannot end that wait)."""
    try:
        family = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0][0]
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.bind((host, 0))
    except (OSError, UnicodeError) as error:
        raise ValueError(f"cannot serve the page on host {host!r}: {error}") from None


class Viewer:
    """A viser server showing the badf workers' objects. `start()` serves the page and starts the refresh
    thread; `close()` stops both and the Zenoh session (or use it as a context manager)."""

    def __init__(self, settings: ViewerSettings) -> None:
        viser = _import_viser()
        self.settings = settings
        check_host(settings.host)  # viser waits forever on a host it cannot bind
        self._client = Client(
            settings.connect, namespace=settings.namespace, timeout=settings.timeout_s, config_file=settings.config_file
        )
        try:
            self._server = viser.ViserServer(host=settings.host, port=settings.port, verbose=False)
        except BaseException:
            self._client.close()
            raise
        self._server.scene.set_up_direction(settings.up)
        self._wake = threading.Condition()
        self._woken = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="badf-viewer-refresh", daemon=True)
        self._lock = threading.Lock()  # guards what status() reads
        self._objects: tuple[str, ...] = ()
        self._shown: _Shown | None = None
        self._known_frame = -1
        self._slices_drawn = 0
        self._meshes_drawn = 0
        self._requests = 0
        self._watching = False
        self._problem: str | None = None
        self._slice_times: deque[tuple[float, float, float]] = deque(maxlen=50)  # (drawn at, round trip, draw) s
        self._handles: dict[str, Any] = {}  # scene nodes by role
        self._build_gui()
        self._server.on_client_connect(self._on_client_connect)

    # --- life cycle and what others may ask -------------------------------------------------------------

    def __enter__(self) -> Viewer:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._poke()
        if self._thread.is_alive():
            self._thread.join(timeout=2 * self.settings.timeout_s + 5)
        self._server.stop()
        self._client.close()

    @property
    def port(self) -> int:
        return self._server.get_port()

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.settings.host in ("0.0.0.0", "::") else self.settings.host
        return f"http://{host}:{self.port}/"

    @property
    def server(self) -> Any:
        """The viser server (for a test's or a benchmark's `get_clients()` and `get_render`)."""
        return self._server

    def set_view(
        self,
        *,
        object_name: str | None = None,
        axis: str | None = None,
        position: float | None = None,
        resolution: int | None = None,
        cells: bool | None = None,
        corners: bool | None = None,
        mesh: bool | None = None,
    ) -> None:
        """Set the page's controls as a user would (None leaves one as it is); the page follows."""
        if object_name is not None:
            self._object_choice.value = check_name(object_name)
        if axis is not None:
            if axis not in AXES:
                raise ValueError(f"axis must be one of {', '.join(AXES)}, got {axis!r}")
            self._axis.value = axis
        if position is not None:
            if not math.isfinite(position):
                raise ValueError(f"position must be a finite number, got {position!r}")
            self._position.value = float(position)
        if resolution is not None:
            if resolution not in RESOLUTIONS:
                raise ValueError(f"resolution must be one of {', '.join(map(str, RESOLUTIONS))}, got {resolution!r}")
            self._resolution.value = str(resolution)
        for handle, value in ((self._show_cells, cells), (self._show_corners, corners), (self._show_mesh, mesh)):
            if value is not None:
                handle.value = bool(value)
        self._poke()

    def status(self) -> ViewerStatus:
        with self._lock:
            shown, times = self._shown, list(self._slice_times)
            view = None if shown is None else shown.slice_view
            recent = [t[0] for t in times if t[0] > time.monotonic() - 2.0]
            return ViewerStatus(
                object_name=None if shown is None else shown.remote.name,
                objects=self._objects,
                depth=None if shown is None else shown.depth,
                known_frame=self._known_frame,
                slice_frame=None if shown is None else shown.slice_frame,
                slice_axis=None if view is None else view.axis,
                slice_position=None if view is None else view.position,
                corner_points=0 if shown is None else shown.corner_points,
                mesh_frame=None if shown is None else shown.mesh_frame,
                slices_drawn=self._slices_drawn,
                meshes_drawn=self._meshes_drawn,
                requests=self._requests,
                watching=self._watching,
                round_trip_ms=float(np.median([t[1] for t in times]) * 1e3) if times else None,
                draw_ms=float(np.median([t[2] for t in times]) * 1e3) if times else None,
                slices_per_s=(len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 else 0.0,
                recent_slices_ms=tuple((t[1] * 1e3, t[2] * 1e3) for t in times),
                scale=None if shown is None else shown.scale,
                problem=self._problem,
            )

    # --- the page's controls: callbacks only record and wake -----------------------------------------

    def _build_gui(self) -> None:
        gui = self._server.gui
        gui.configure_theme(control_width="large")
        gui.main_panel.dock_right()  # beside the canvas, not over it
        with gui.add_folder("Object"):
            self._object_choice = gui.add_dropdown("object", (NO_OBJECT,), initial_value=NO_OBJECT)
            self._show_mesh = gui.add_checkbox("mesh", True, hint="the object's newest applied vertices")
            self._mesh_opacity = gui.add_slider(
                "mesh opacity", 0.0, 1.0, 0.05, 1.0, hint="below 1, parts behind the slice may show through it"
            )
            self._panel = gui.add_markdown("waiting for a browser")
        with gui.add_folder("Slice"):
            self._axis = gui.add_dropdown("axis", AXES, initial_value="z")
            self._position = gui.add_slider("position", -1.0, 1.0, 0.001, 0.0, hint="world units")
            self._resolution = gui.add_dropdown(
                "resolution", tuple(str(r) for r in RESOLUTIONS), initial_value=str(self.settings.resolution)
            )
            self._auto_scale = gui.add_checkbox(
                "auto scale", True, hint="deepest inside, or a quarter of the farthest outside, rounded up"
            )
            self._scale = gui.add_number("scale +-", 1.0, min=1e-9, step=1e-5, hint="object units", disabled=True)
            self._legend = gui.add_html(legend_html(1.0))
        with gui.add_folder("Octree"):
            self._show_cells = gui.add_checkbox("cells", True, hint="the octree cells the plane crosses")
            self._levels = gui.add_multi_slider("levels", 0, 10, 1, (0, 10), min_range=0)
            self._show_corners = gui.add_checkbox(
                "corner samples", False, hint="the 8 corners of each leaf the plane crosses, coloured by their value"
            )
        inputs = (
            self._object_choice, self._show_mesh, self._mesh_opacity, self._position, self._resolution,
            self._scale, self._show_cells, self._levels, self._show_corners,
        )  # fmt: skip
        for handle in inputs:
            handle.on_update(lambda _event: self._poke())
        self._axis.on_update(lambda _event: self._on_axis())
        self._auto_scale.on_update(lambda _event: self._on_auto_scale())

    def _on_axis(self) -> None:
        shown = self._shown
        if shown is not None:
            self._fit_position_slider(shown)
        self._poke()

    def _on_auto_scale(self) -> None:
        self._scale.disabled = self._auto_scale.value
        self._poke()

    def _on_client_connect(self, client: Any) -> None:
        shown = self._shown
        if shown is not None:
            self._aim_camera(client.camera, shown)
        self._poke()

    def _poke(self) -> None:
        with self._wake:
            self._woken = True
            self._wake.notify_all()

    def _wanted_view(self, shown: _Shown) -> SliceView:
        low, high = (int(level) for level in self._levels.value)
        return SliceView(
            axis=self._axis.value,
            position=float(self._position.value),
            resolution=int(self._resolution.value),
            levels=(min(low, shown.depth), min(high, shown.depth)),
            cells=bool(self._show_cells.value),
            corners=bool(self._show_corners.value),
            scale=None if self._auto_scale.value else float(self._scale.value),
        )

    def _fit_position_slider(self, shown: _Shown) -> None:
        """The position slider spans the domain along the chosen axis and starts at the object's middle."""
        axis = AXES.index(self._axis.value)
        self._position.min = float(shown.centre[axis] - shown.side / 2)
        self._position.max = float(shown.centre[axis] + shown.side / 2)
        self._position.step = float(shown.side / (1 << shown.depth) / 8)
        self._position.value = float(shown.box_centre[axis])

    # --- the refresh thread ---------------------------------------------------------------------------

    def _run(self) -> None:
        due = _Due()
        sleep_s = 0.0
        while not self._stop.is_set():
            with self._wake:
                if not self._woken:
                    self._wake.wait(timeout=sleep_s)
                self._woken = False
            if self._stop.is_set():
                break
            watching = self.settings.watch_without_browser or bool(self._server.get_clients())
            with self._lock:
                self._watching = watching
            if not watching:
                sleep_s = _RETRY_PERIOD_S  # nobody is looking: ask the workers nothing (a browser wakes us)
                continue
            try:
                sleep_s = self._turn(due)
                self._set_problem(None)
            except WorkerBusyError:
                sleep_s = due.hold_back(0.05)
            except BadfError as error:
                self._set_problem(f"{type(error).__name__}: {error.message}")
                if isinstance(error, (ObjectNotFoundError, ObjectUnavailableError)):
                    # gone, or its worker is: open it again by name, wherever it is registered now
                    self._forget_object()
                    due.listing = 0.0
                sleep_s = due.hold_back(_RETRY_PERIOD_S)
            except Exception as error:  # noqa: BLE001 - a bug here must not leave the page frozen without a word
                log.exception("the viewer's refresh failed")
                self._set_problem(f"internal error in the viewer: {type(error).__name__}: {error}")
                sleep_s = due.hold_back(_RETRY_PERIOD_S)

    def _turn(self, due: _Due) -> float:
        """Do what is due; return how long to sleep until the next thing is (a GUI change wakes us sooner)."""
        settings = self.settings
        now = time.monotonic()
        if due.listing <= now:
            self._refresh_listing()
            due.listing = now + _LISTING_PERIOD_S
        chosen = self._object_choice.value
        shown = self._shown
        if chosen == NO_OBJECT:
            if shown is not None:
                self._forget_object()
            self._panel.content = f"no objects on the workers of namespace `{settings.namespace}` yet"
            return due.listing - now
        if shown is None or shown.remote.name != chosen:
            shown = self._open(chosen)
            due.restart()
        if due.info <= now:
            self._count_requests()
            try:
                info = shown.remote.info()
            except ObjectNotFoundError:
                # the handle's registration was deleted or replaced (a handle names its registration): open the
                # name again, whose faces, depth and frame numbers may all differ; if it is gone, that raises
                shown = self._open(chosen)
                info = shown.info
            shown.info = info
            self._saw_frame(info.frame)
            due.info = now + 1 / settings.max_info_hz
        if due.panel <= now:
            self._panel.content = self._panel_text(shown)
            due.panel = now + _PANEL_PERIOD_S
        self._apply_mesh_controls()
        mesh_wanted = bool(self._show_mesh.value) and self._known_frame > shown.mesh_frame
        if mesh_wanted and due.mesh <= now:
            self._draw_mesh(shown)
            due.mesh = now + 1 / settings.max_mesh_hz
            mesh_wanted = False
        view = self._wanted_view(shown)
        slice_wanted = view != shown.slice_view or shown.slice_frame is None or self._known_frame > shown.slice_frame
        if slice_wanted and due.slice <= now:
            self._draw_slice(shown, view)
            due.slice = now + 1 / settings.max_slice_hz
            slice_wanted = False
        next_due = min([due.info, due.panel, due.listing] + [due.mesh] * mesh_wanted + [due.slice] * slice_wanted)
        return max(0.0, next_due - time.monotonic())

    def _refresh_listing(self) -> None:
        self._count_requests()
        names = tuple(info.name for info in self._client.objects())
        with self._lock:
            self._objects = names
        options = names or (NO_OBJECT,)
        current = self._object_choice.value
        if tuple(self._object_choice.options) != options:
            self._object_choice.options = options
        if current not in options or (current == NO_OBJECT and names):
            preferred = self.settings.object_name
            self._object_choice.value = preferred if preferred in options else options[0]

    def _open(self, name: str) -> _Shown:
        """Make `name` the object on screen: its info, domain and mesh; the controls and camera fit it."""
        self._forget_object()
        self._count_requests(3)
        remote = self._client.object(name)
        info = remote.info()
        mesh = remote.mesh(faces=True)
        domain = info.field_info.get("domain", {})
        low, high = mesh.vertices.min(axis=0).astype(np.float64), mesh.vertices.max(axis=0).astype(np.float64)
        shown = _Shown(
            remote=remote,
            info=info,
            centre=np.asarray(domain.get("centre", (low + high) / 2), dtype=np.float64),
            side=float(domain.get("side", np.max(high - low))),
            depth=int(info.field_info.get("depth", info.options.depth)),
            faces=np.array(mesh.faces),
            mesh_frame=mesh.frame,
            box_centre=(low + high) / 2,
        )
        self._levels.max = shown.depth
        self._levels.value = (0, shown.depth)
        self._fit_position_slider(shown)
        self._handles["mesh"] = self._server.scene.add_mesh_simple(
            "/object/mesh", np.array(mesh.vertices, np.float32), shown.faces, color=MESH_RGB,
            opacity=_opacity(self._mesh_opacity.value), side="double", cast_shadow=False, receive_shadow=False,
            visible=bool(self._show_mesh.value),
        )  # fmt: skip
        camera = self._server.initial_camera
        camera.near = shown.side / 500
        self._aim_camera(camera, shown)
        for client in self._server.get_clients().values():
            self._aim_camera(client.camera, shown)
        with self._lock:
            self._shown = shown
            self._known_frame = max(info.frame, mesh.frame)
            self._meshes_drawn += 1
        return shown

    def _forget_object(self) -> None:
        for name in list(self._handles):
            self._handles.pop(name).remove()
        with self._lock:
            self._shown = None
            self._known_frame = -1

    def _saw_frame(self, frame: int) -> None:
        with self._lock:
            self._known_frame = max(self._known_frame, frame)

    def _count_requests(self, count: int = 1) -> None:
        with self._lock:
            self._requests += count

    def _set_problem(self, problem: str | None) -> None:
        with self._lock:
            changed = problem != self._problem
            self._problem = problem
        if changed and problem is not None:
            self._panel.content = f"**{problem}**\n\nasking again in {_RETRY_PERIOD_S:g} s"

    # --- drawing -------------------------------------------------------------------------------------

    def _aim_camera(self, camera: Any, shown: _Shown) -> None:
        """Frame the octree's domain (which the slice plane spans), looking mostly across the slice plane and a
        little from above."""
        up, facing = "xyz".index(self.settings.up[1]), AXES.index(self._axis.value)
        toward = np.full(3, 0.6)
        toward[facing] = 1.0
        if facing != up:
            toward[up] = 0.4
        toward[up] *= 1.0 if self.settings.up[0] == "+" else -1.0
        camera.look_at = tuple(shown.centre)
        camera.position = tuple(shown.centre + 1.1 * shown.side * toward / np.linalg.norm(toward))

    def _apply_mesh_controls(self) -> None:
        handle = self._handles.get("mesh")
        if handle is None:
            return
        visible, opacity = bool(self._show_mesh.value), _opacity(self._mesh_opacity.value)
        if handle.visible != visible:
            handle.visible = visible
        if handle.opacity != opacity:
            handle.opacity = opacity

    def _draw_mesh(self, shown: _Shown) -> None:
        self._count_requests()
        mesh = shown.remote.mesh(faces=False)
        self._saw_frame(mesh.frame)
        self._handles["mesh"].vertices = np.array(mesh.vertices, np.float32)  # float64 if the client sent it
        shown.mesh_frame = mesh.frame
        with self._lock:
            self._meshes_drawn += 1

    def _draw_slice(self, shown: _Shown, view: SliceView) -> None:
        self._count_requests()
        asked = time.perf_counter()
        cut = shown.remote.slice(
            view.axis, view.position, resolution=view.resolution, levels=view.levels, cells=view.cells
        )
        received = time.perf_counter()
        self._saw_frame(cut.frame)
        scale = view.scale if view.scale is not None else auto_scale(cut.grid)
        corners = None
        if view.corners and cut.cell_boxes is not None:
            corners = self._corner_samples(shown, cut)
        with self._server.atomic():
            self._draw_slice_nodes(shown, cut, scale, corners)
        if scale != shown.scale:
            self._legend.content = legend_html(scale)
            if view.scale is None:
                self._scale.value = scale
        drawn = time.perf_counter()
        with self._lock:
            shown.slice_view, shown.slice_frame, shown.scale = view, cut.frame, scale
            shown.corner_points = 0 if corners is None else len(corners[0])
            self._slice_times.append((time.monotonic(), received - asked, drawn - received))
            self._slices_drawn += 1

    def _corner_samples(self, shown: _Shown, cut: SliceReply) -> tuple[np.ndarray, np.ndarray] | None:
        """The corners of the leaves on the plane and the field sampled at each (a query of the worker)."""
        corners, probes = leaf_corners(cut.cell_boxes, cut.cell_flags)
        if len(corners) == 0 or len(corners) > MAX_CORNER_POINTS:
            return None
        self._count_requests()
        values = shown.remote.query(probes, mode="adf", outputs=("distance",)).distance
        return corners, values

    def _draw_slice_nodes(
        self, shown: _Shown, cut: SliceReply, scale: float, corners: tuple[np.ndarray, np.ndarray] | None
    ) -> None:
        scene = self._server.scene
        plane = PlaneFrame(cut.axis, cut.position, cut.extent)
        wxyz, centre, width, height = plane.image_pose()
        image = diverging_rgb(cut.grid, scale)
        handle = self._handles.get("image")
        if handle is None:
            self._handles["image"] = scene.add_image(
                "/slice/image", image, width, height, format="jpeg", jpeg_quality=_JPEG_QUALITY, wxyz=wxyz,
                position=centre,
                cast_shadow=False, receive_shadow=False,
            )  # fmt: skip
        else:  # updated in place, so the browser keeps the old picture until the new one is decoded
            handle.image = image
            handle.wxyz, handle.position = wxyz, centre
            handle.render_width, handle.render_height = width, height
        lift = shown.side * _LIFT
        contour = on_both_sides(zero_contour(cut.grid, plane), plane, lift)
        self._replace_lines("contour", contour, ZERO_CONTOUR_RGB, thickness=2.5)
        if cut.cell_boxes is not None:
            outlines = on_both_sides(cell_outlines(cut.cell_boxes, plane), plane, lift)
            edge_rgb = np.repeat(level_rgb(cut.cell_levels, shown.depth), 4, axis=0)  # 4 edges a cell
            rgb = np.concatenate([edge_rgb, edge_rgb])  # both sides, as on_both_sides orders them
            self._replace_lines("cells", outlines, np.repeat(rgb[:, None, :], 2, axis=1), thickness=1.0)
        else:
            self._remove("cells")
        self._remove("corners")
        if corners is not None:
            points, values = corners
            self._handles["corners"] = scene.add_point_cloud(
                "/slice/corners", points, diverging_rgb(values, scale),
                point_size=shown.side / (1 << shown.depth) / 6, point_shape="circle", point_shading="flat",
                precision="float32",
            )  # fmt: skip

    def _replace_lines(self, key: str, segments: np.ndarray, colors: Any, *, thickness: float) -> None:
        self._remove(key)
        if len(segments):
            self._handles[key] = self._server.scene.add_line_segments(
                f"/slice/{key}", segments, colors, thickness=thickness, thickness_units="screen"
            )

    def _remove(self, key: str) -> None:
        handle = self._handles.pop(key, None)
        if handle is not None:
            handle.remove()

    # --- the panel -----------------------------------------------------------------------------------

    def _panel_text(self, shown: _Shown) -> str:
        info, status = shown.info, self.status()
        stats = info.field_stats
        counts = stats.get("counts", {})
        memory = stats.get("device_bytes")
        slice_line = "slice: none yet"
        if status.round_trip_ms is not None:
            slice_line = (
                f"slice {status.round_trip_ms:.1f} ms round trip + {status.draw_ms:.1f} ms drawing; "
                f"{status.slices_per_s:.1f} slices/s"
            )
        lines = [
            f"**{info.name}** on worker `{info.worker}` ({info.field_info.get('device', '?')})",
            f"frame **{info.frame}** (slice of {_text(shown.slice_frame)}, mesh of {shown.mesh_frame}); "
            f"{info.frames_applied} applied, {info.frames_dropped} dropped",
            f"update {_ms(stats.get('update_wall_ms'))}, last slice {_ms(stats.get('last_slice_ms'))}, "
            f"last query {_ms(stats.get('last_query_ms'))} (worker)",
            slice_line,
            f"{info.face_count:,} triangles, {counts.get('octree_nodes', 0):,} octree nodes, "
            f"{counts.get('unique_corners', 0):,} corners",
            f"memory {memory / 2**20:.1f} MiB on the device" if isinstance(memory, (int, float)) else "memory ?",
        ]
        if shown.scale is not None:
            lines.append(f"colours from {format_distance(-shown.scale)} to {format_distance(shown.scale)}")
        return "  \n".join(lines)


def _opacity(value: float) -> float | None:
    """viser's opacity: None draws the mesh opaque (sorted with the slice by depth, not by distance)."""
    return None if value >= 1.0 else float(value)


def _ms(value: object) -> str:
    return f"{value:.2f} ms" if isinstance(value, (int, float)) else "?"


def _text(value: object) -> str:
    return "-" if value is None else str(value)


class _Due:
    """When each kind of request may next go out, in time.monotonic() seconds."""

    def __init__(self) -> None:
        self.listing = 0.0
        self.restart()

    def restart(self) -> None:
        self.info = self.panel = self.mesh = self.slice = 0.0

    def hold_back(self, seconds: float) -> float:
        """Let no request go out for `seconds`; returns `seconds`."""
        later = time.monotonic() + seconds
        for name in ("listing", "info", "mesh", "slice"):
            setattr(self, name, max(getattr(self, name), later))
        return seconds
