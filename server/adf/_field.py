"""DistanceField: one triangle mesh and its adaptive distance field on one device."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import warp as wp

from badf.server._environment import cpu_threads_setting
from badf.server.adf._buffers import DeviceBuffers, HostStaged, SideStream
from badf.server.adf._bvh import SPREAD_UNIT, TREE_DUE, TREE_MISFITS, Bvh, spread_units, tree_fit
from badf.server.adf._bvh_shape import Shape, resolve_shape, sah_shape
from badf.server.adf._clock import StageClock
from badf.server.adf._distance import (
    OUT_CLOSEST,
    OUT_NORMAL,
    OUTPUT_BITS,
    CornerField,
    PointQuery,
    mark_medial_leaves,
    mark_rim_leaves,
)
from badf.server.adf._inputs import (
    BVH_SHAPES,
    MAX_COORDINATE,
    MIN_EXTENT,
    QUERY_MODES,
    REFINEMENTS,
    InvalidInputError,
    as_faces,
    as_points,
    as_vertices,
    check_band,
    check_choice,
    check_depth,
    check_flag,
    check_axis,
    check_finite_number,
    check_halo,
    check_region,
    check_level,
    check_outputs,
    check_resolution,
)
from badf.server.adf._octree import Octree
from badf.server.adf._rigid import RIGID_MODES, Pose, RigidTest
from badf.server.adf._slice import AXES, Slice, SliceCells, plane_grid
from badf.server.adf._sign import (
    SIGN_METHODS,
    Pseudonormals,
    analyse_topology,
    beside_points,
    components_disagree,
    encloses_volume,
    face_components,
    face_volumes,
    frame_watch_order,
    resolve_sign,
    rim_edge_vertices,
    rim_fans,
    spread_sample,
    surface_enters_solid,
    with_fans,
)
from badf.server.adf._tolerances import (
    CENTRE_SNAP,
    DOMAIN_MARGIN,
    FAR_POINT,
    MAX_KERNEL_BAND,
    MIN_BAND,
    QUERY_CHUNK,
    REDOMAIN_KEEP_SIDE,
    REDOMAIN_MIN_FILL,
    REDOMAIN_REFIT_ROOM,
    RIM_LIMIT,
    RIGID_TOLERANCE,
    SOLID_BESIDE_SAMPLE,
    SOLID_WATCH_SAMPLE,
)

log = logging.getLogger("badf.server")

# A first frame planned from an estimate of its sizes keeps the estimate's buffers until the next frame gives
# back what they hold beyond its plan, unless they held more than this many times that plan: it is then run
# again at once (`DistanceField._planned_frame`).
_ESTIMATE_KEPT = 2.0

# A plan that held more than _PLAN_GIVEN_BACK_OVER times what each of _PLAN_GIVEN_BACK_AFTER frames in a row needed
# (after a violent frame: a soup, a throw, a cloth that blew up and settled) is given back: later frames are planned
# for the largest of those frames, and the next one sizes the buffers anew (`DistanceField._watch_plan`). Until then a
# planned frame's hash tables, lists and sorts keep the violent frame's sizes: spot at depth 6 held 13.2 MiB against
# 5.3 after a soup frame, and its calm updates took 10% longer on the CPU, for as long as the object lived.
_PLAN_GIVEN_BACK_OVER = 2.0
_PLAN_GIVEN_BACK_AFTER = 30

# After this many rigid frames in a row (rigid="auto": the field kept, nothing rebuilt), the frame scratch that only a
# rebuild uses (the octree's stages' shared allocation, 5.9 MiB of the bunny's 32.5 at depth 7) is given back; the next
# rebuild allocates it again and runs eagerly before its frame is captured again (`DistanceField._take_rigid_frame`).
_SCRATCH_GIVEN_BACK_AFTER = 30

# One lock per device: Warp's CUDA sorts keep per-device scratch in native code and its launches are not
# documented as thread-safe, so engine work on a device is serialised across threads (a worker serves each
# object from its own thread). The device runs one stream in order anyway; only host-side work loses overlap.
_DEVICE_LOCKS: dict[str, threading.RLock] = {}
_LOCKS_GUARD = threading.Lock()


def _device_lock(device: wp.Device) -> threading.RLock:
    with _LOCKS_GUARD:
        return _DEVICE_LOCKS.setdefault(str(device), threading.RLock())


def _on_device(method):
    """Run a DistanceField method holding its device's lock; on the CPU back-end a bad BADF_CPU_THREADS is refused
    first, before the method touches anything (it would fail mid-frame, at the first launch shared out)."""

    @functools.wraps(method)
    def locked(self, *args, **kwargs):
        if self._device.is_cpu:
            cpu_threads_setting()
        with _device_lock(self._device):
            return method(self, *args, **kwargs)

    return locked


QueryMode = Literal["adf", "exact"]
QueryOutput = Literal["distance", "closest_point", "normal", "face"]


class FieldUnavailableError(RuntimeError):
    """An update failed after its input was checked (out of device memory, say): until one succeeds, the
    object has no consistent field to answer from."""


@dataclass
class QueryResult:
    """Answers for P points; only the outputs asked for are filled, the others are None.

    distance: (P,) float32 signed distance, negative inside (unsigned when the sign is "none"); clamped to
        +-band when a band is set.
    closest_point: (P, 3) float32 nearest surface point (adf mode: p - distance * normal); (0, 0, 0) beyond
        the band, where there is none.
    normal: (P, 3) float32 unit gradient of the field; zero where it is flat (beyond the band).
    face: (P,) int32 index of the nearest face; -1 beyond the band (adf mode: the face nearest the
        cell corner closest to p).
    frame: the frame the answers are for.
    """

    distance: np.ndarray | None = None
    closest_point: np.ndarray | None = None
    normal: np.ndarray | None = None
    face: np.ndarray | None = None
    frame: int = 0


@dataclass(frozen=True)
class _Domain:
    """The cube the octree covers: centre (float64) and side length.

    The device works in local coordinates: (world - centre) * scale, where scale is the power of two nearest
    1 / side, so the domain's side is between 0.7 and 1.4 there whatever the mesh's size. Multiplying by a
    power of two is exact in floating point, so every distance is the world one times scale to the bit,
    while the kernels' squares and cubes of lengths stay far from float32's overflow and underflow (a
    triangle of edge 1e7 or 1e-7 would otherwise reach them).

    The centre is snapped to a float32 number where that moves it by little against the side, so float32
    frames and points can be recentred on the device in float32 (`recentres_float32`). A mesh small against
    float32's spacing where it lies (1 unit at 1e9, 1e-3 at 1e6) keeps its float64 centre instead, and is
    recentred on the host in float64: snapping would have widened its domain by the rounding, many times
    its size, coarsening the octree and moving the domain every frame.
    """

    centre: np.ndarray
    side: float
    scale: float
    float32_centre: bool = True

    @staticmethod
    def fit(lo: np.ndarray, hi: np.ndarray, previous: _Domain | None = None) -> _Domain:
        extent = float(np.max(hi - lo))
        if extent >= MIN_EXTENT:
            side = extent * (1.0 + 2.0 * DOMAIN_MARGIN)
        elif extent > 0.0:
            raise InvalidInputError(
                f"the mesh's extent is {extent:.3g}; meshes smaller than {MIN_EXTENT:g} are refused (answers are "
                "float32 in world units, whose smallest step, 1.4e-45, would pass 1e-5 of its size): scale it up")
        elif previous is not None:  # a frame that collapses to a point keeps the cube's size
            side = previous.side
        else:
            raise InvalidInputError("the vertices the faces use must not all coincide: the mesh has zero extent")
        centre = (lo.astype(np.float64) + hi.astype(np.float64)) / 2.0
        snapped = centre.astype(np.float32).astype(np.float64)
        shift = float(np.max(np.abs(snapped - centre)))
        float32_centre = shift <= CENTRE_SNAP * side
        if float32_centre:
            centre = snapped
            side += 2.0 * shift  # the centre's float32 rounding must not push the mesh out of the cube
        if previous is not None and side <= previous.side <= REDOMAIN_KEEP_SIDE * side:
            # a move that keeps the side, and lattice: the cube is never smaller than a fresh fit's, so it holds
            # every later frame that a fresh fit would (one a rounding smaller bounced between two centres)
            return _Domain(centre, previous.side, previous.scale, float32_centre)
        if previous is not None and side > previous.side:
            side *= REDOMAIN_REFIT_ROOM  # a mesh that grew may grow on: room for later moves, which then keep it
        return _Domain(centre, side, math.ldexp(1.0, -round(math.log2(side))), float32_centre)

    def holds(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        half = self.side / 2.0
        inside = bool(np.all(lo >= self.centre - half) and np.all(hi <= self.centre + half))
        return inside and float(np.max(hi - lo)) >= REDOMAIN_MIN_FILL * self.side

    def to_local_float64(self, points: np.ndarray) -> np.ndarray:
        """Local coordinates of world points, in float64."""
        return (np.asarray(points, dtype=np.float64) - self.centre) * self.scale

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """Local float32 coordinates of world points, recentred in their own precision (float64 stays exact;
        float32 goes through float64 where the centre or the scale is not a float32 number)."""
        # a vertex no face uses may lie far enough (1e18 beside a mesh of 1e-24) to pass float32's range here: it
        # becomes Inf, which nothing reads, and numpy's overflow warning is not the caller's concern
        with np.errstate(over="ignore"):
            if self.recentres_float32:
                local = (points - self.centre.astype(points.dtype)) * self.scale
            else:
                local = self.to_local_float64(points)  # numpy would round float32 offsets to float32
            return np.ascontiguousarray(local, dtype=np.float32)

    @property
    def recentres_float32(self) -> bool:
        """Whether the centre, the scale and its inverse are float32 numbers, so float32 arithmetic (numpy's,
        the device's) can recentre float32 points exactly as the host's float64 would round them. Not for a
        mesh smaller than about 1e-38 (scale above 2^127), nor one with a float64 centre (see the class)."""
        return self.float32_centre and _float32_holds(self.scale) and _float32_holds(1.0 / self.scale)

    @property
    def local_side(self) -> float:
        return self.side * self.scale

    def local_band(self, band: float | None) -> float | None:
        """A band in local units, at least MIN_BAND of the side (so its square stays a normal float32) and at
        most MAX_KERNEL_BAND sides (beyond every distance the kernels meet, and within float32's range)."""
        if band is None:
            return None
        return min(max(band * self.scale, MIN_BAND * self.local_side), MAX_KERNEL_BAND * self.local_side)

    def band_in_force(self, band: float | None) -> float | None:
        """The band distances are clamped at, in world units: the kernels' (`local_band`, as the float32 they
        take), or the one asked for where that is wider than any distance they meet (far points only)."""
        local = self.local_band(band)
        if local is None:
            return None
        if local >= MAX_KERNEL_BAND * self.local_side:
            return float(band)
        return float(np.float32(local)) / self.scale

    @functools.cached_property
    def origin(self) -> wp.vec3:
        """The cube's lowest corner in local coordinates (one object per domain, so that the views made of it are
        kept: `KeptViews`)."""
        half = self.local_side / 2.0
        return wp.vec3(-half, -half, -half)


@dataclass
class _Counters:
    updates: int = 0
    domain_moves: int = 0
    queries: int = 0
    query_points: int = 0
    last_query_ms: float = 0.0
    slices: int = 0
    last_slice_ms: float = 0.0
    last_update_wall_ms: float = 0.0
    replans: int = 0  # planned frames that outgrew their sizes and were measured again
    measured_frames: int = 0  # frames that read their sizes back on the way: every replan, and a first frame
    # that could not be planned from an estimate (refine="centroid", an area the first try's caps cut, or too
    # many corners to plan for)
    graph_captures: int = 0
    rigid_frames: int = 0  # frames answered by moving the queries into the field of an earlier frame (rigid="auto")
    rigid_rebuilds: int = 0  # fields rebuilt for such a frame because a slice or a tool needed it in place
    plans_given_back: int = 0  # plans that long held far more than the frames needed, sized down (_watch_plan)
    scratch_given_back: int = 0  # runs of rigid frames long enough that the frame scratch was freed until a rebuild
    trims: int = 0  # calls of trim() that gave memory back
    # the last frame's winding-number walks cut short by their budget (WINDING_BUDGET). On the CPU back-end, whose
    # chunks of walks run side by side and whose atomic adds are not atomic between them, the count may fall a few
    # short (15,846 to 15,849 for one frame); only whether it is zero decides anything
    winding_walks_cut: int = 0
    bvh_relinks: int = 0  # frames that linked the BVH again, which had come to misfit the frames (_relink_due)


class DistanceField:
    """Adaptive signed distance field of a triangle mesh, rebuilt frame by frame on one device.

    Args:
        vertices: (N, 3) vertex positions, any float or int dtype; finite.
        faces: (M, 3) integer vertex indices, M >= 1.
        depth: finest octree level, 1..10 (2**depth cells per axis of the domain cube at the finest level).
        sign: "pseudonormal" (angle-weighted, needs a closed mesh), "winding" (generalised winding number,
            any mesh), "none" (unsigned, e.g. cloth), or "auto" (pseudonormal for a closed mesh that encloses
            volume, else winding). Negative inside.
        band: if set, distances beyond it are clamped to +-band and the searches stop at it. An ADF query in a
            leaf with corners clamped and not, reading inside the band, is answered exactly.
        coherence: start each frame's corner searches from last frame's nearest faces.
        refine: "surface" refines every finest cell the surface crosses; "centroid" only the cells holding a
            triangle's centroid (the paper's rule, with halo=0).
        halo: finest cells of refinement added around those, 0..2. With 1 (the default) every point within
            one finest cell of the surface is interpolated in a finest cell of exact corners.
        region: None, or a box [[xmin, ymin, zmin], [xmax, ymax, zmax]] in the mesh's coordinates (a region
            of interest: a robot's workspace, the part of a scene a simulation touches). The octree is refined
            only where the box needs it; ADF queries outside the box are answered exactly, as beyond the
            domain. The domain still fits the mesh, so depth means the same cells.
        bvh: the shape of the BVH the searches and winding numbers walk: "morton" (Karras's radix tree over the
            triangles' Morton codes, the paper's, linked on the device), "sah" (split by the surface area
            heuristic, made once on the host at registration and kept, its boxes refit every frame: faster
            frames and exact queries, for a registration that takes longer), or "auto" (sah on the CPU
            back-end, where it pays within a few frames; morton on CUDA). docs/engine.md, "The BVH's shape".
        rigid: "auto" (the default) keeps the field for a frame that only turns and shifts the whole mesh (every
            used vertex within RIGID_TOLERANCE, 1e-6, of the bounding box's diagonal of one rigid motion of the
            last rebuilt frame) and answers its queries by moving them into it: no refit, no rebuild, no device
            work. A slice or the corner and cell lists rebuild it in place first. "off" rebuilds every frame.
            Not with a region, which is fixed in the mesh's coordinates. docs/engine.md, "Rigid frames".
        device: "cpu", "cuda", "cuda:N", or None for the first GPU if there is one, else the CPU.

    Raises:
        InvalidInputError: on bad input; nothing is kept from the failed call.
    """

    def __init__(
        self,
        vertices,
        faces,
        *,
        depth: int = 7,
        sign: Literal["auto", "pseudonormal", "winding", "none"] = "auto",
        band: float | None = None,
        coherence: bool = True,
        refine: Literal["surface", "centroid"] = "surface",
        halo: int = 1,
        region=None,
        bvh: Literal["auto", "morton", "sah"] = "auto",
        device: str | None = None,
        rigid: Literal["auto", "off"] = "auto",
    ):
        v = as_vertices(vertices)
        f = as_faces(faces, len(v))
        self._depth = check_depth(depth)
        self._sign_requested = check_choice(sign, "sign", SIGN_METHODS)
        self._band = check_band(band)
        self._coherence = check_flag(coherence, "coherence")
        self._refine = check_choice(refine, "refine", REFINEMENTS)
        self._halo = check_halo(halo)
        self._region = check_region(region)
        self._bvh_requested = check_choice(bvh, "bvh", BVH_SHAPES)
        self._rigid_mode = check_choice(rigid, "rigid", RIGID_MODES)
        self._device = _resolve_device(device)
        self._bvh_shape = resolve_shape(self._bvh_requested, self._device.is_cpu)
        if self._device.is_cpu:
            cpu_threads_setting()  # a bad BADF_CPU_THREADS, refused before anything is built

        # vertices no face uses (left over from editing, or parked far away) have no say in the domain
        used = np.zeros(len(v), dtype=bool)
        used[f] = True
        self._used = None if used.all() else np.flatnonzero(used)
        lo, hi = self._bounds(v)
        self._domain = _Domain.fit(lo, hi)
        if self._band is not None and self._band < MIN_BAND * self._domain.side:
            raise InvalidInputError(
                f"band must be at least {MIN_BAND * self._domain.side:.3g} ({MIN_BAND:.3g} of the domain's side "
                f"{self._domain.side:.3g}, about what float32 resolves there), got {self._band!r}")
        local = self._domain.to_local(v)
        extent = float(np.max(hi - lo)) * self._domain.scale  # in local units, as everything on the device
        # the fans, half of the analysis, at once where pseudonormals were asked for, else once auto resolves to them
        fans = self._sign_requested == "pseudonormal"
        self._topology = analyse_topology(f, v, fans=fans)
        face_volume, face_area = face_volumes(local, f)
        volume, area = float(face_volume.sum()), float(face_area.sum())
        solid = self._topology.closed and encloses_volume(volume, area, extent)
        parts = face_components(self._topology) if solid else None
        # a part inside out beside the others (or a cavity) is signed by winding numbers (components_disagree)
        self._parts_disagree = bool(solid and components_disagree(face_volume, face_area, parts, extent))
        solid = solid and not self._parts_disagree
        self._flipped = bool(solid and volume < 0.0)
        if self._flipped:
            f = np.ascontiguousarray(f[:, [0, 2, 1]])
            # the pseudonormals' corner angles and edge slots are indexed by each face's corner order
            self._topology = analyse_topology(f, v, fans=fans)
        self._sign = resolve_sign(self._sign_requested, self._topology, solid)
        if self._sign == "pseudonormal":
            self._topology = t = with_fans(self._topology, f)
            if not t.closed:
                log.warning("sign='pseudonormal' was asked for a mesh that is not closed (%d open, %d non-manifold "
                            "and %d inconsistently oriented edges): points beside its holes may be signed wrongly; "
                            "sign='auto' or 'winding' signs it by winding numbers", t.boundary_edges,
                            t.nonmanifold_edges, t.inconsistent_edges)
        self._vertex_count, self._face_count = len(v), len(f)
        self._frame = 0
        # rigid frames are tested against the last rebuilt frame (the reference); a region stays where it is in
        # the mesh's coordinates, so a mesh that moves through it needs its field rebuilt
        self._rigid_test = RigidTest(v, self._used) if self._rigid_mode == "auto" and self._region is None else None
        self._pose: Pose | None = None  # the current frame's pose from the reference frame, which the field is of
        # while a pose is held, the current frame, kept to rebuild it in place on demand (the array is kept from
        # frame to frame)
        self._posed_vertices: np.ndarray | None = None
        self._reference: np.ndarray | None = None
        self._keep_reference(v, lo, hi)
        self._rigid_run = 0  # rigid frames since the last rebuild
        self._scratch_kept_frames = _SCRATCH_GIVEN_BACK_AFTER
        self._counters = _Counters()
        # the BVH's leaf spread (Bvh.measure_spread) in the last frame, and how the tree fits it (`tree_fit`, from the
        # frame's report: `_relink_due`)
        self._tree_spread, self._tree_fit = 0.0, 0

        # the first frame's cell set is sized from the surface area it may refine: a region's share of it (a
        # small box at depth 10 kept 452 MiB of scratch sized for the whole mesh; thirteenth outside check)
        refined_area = area if self._region is None else self._area_near_region(local, f, face_area)
        started = time.perf_counter()
        shape = sah_shape(local, f) if self._bvh_shape == "sah" and len(f) > 1 else None
        self._shape_ms = (time.perf_counter() - started) * 1e3 if shape is not None else None
        with _device_lock(self._device):
            self._build(local, f, len(v), refined_area, extent, shape)
            # parts nested or running into each other are signed by winding numbers (surface_enters_solid):
            # every frame, if they are in the first; else each frame they are found to be, from then on
            self._parts_overlap = False
            if self._sign_requested == "auto" and self._sign == "pseudonormal":
                self._parts_overlap = surface_enters_solid(
                    self._bvh.view(), self._normals.view(), self._vertices, self._faces,
                    beside_points(spread_sample(parts, SOLID_BESIDE_SAMPLE), len(f)),
                    self._normals.extent, self._device)
                if not self._parts_overlap:
                    self._normals.watch_parts(frame_watch_order(len(f)), SOLID_WATCH_SAMPLE)
            if self._parts_overlap:
                self._sign = "winding"
                self._normals = Pseudonormals(self._sign, self._topology, self._faces, self._buffers)
                self._planned, self._counters = False, _Counters()
                self._apply(local, extent, domain_moved=True)

    def _area_near_region(self, local: np.ndarray, f: np.ndarray, face_area: np.ndarray) -> float:
        """The area of the faces whose bounding boxes come within the halo (and a cell) of the region."""
        reach = (self._halo + 1) * self._domain.local_side / (1 << self._depth)
        box = self._domain.to_local_float64(self._region)
        corners = local[f]
        near = np.all((corners.max(axis=1) >= box[0] - reach) & (corners.min(axis=1) <= box[1] + reach), axis=1)
        return float(face_area[near].sum())

    def _bounds(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The bounds of the vertices that faces use."""
        return bounds(v if self._used is None else v[self._used])

    def _build(self, local: np.ndarray, f: np.ndarray, vertex_count: int, area: float, extent: float,
               shape: Shape | None) -> None:
        self._buffers = DeviceBuffers(self._device)
        b = self._buffers
        self._vertices = b.array("mesh.vertices", vertex_count, wp.vec3)
        self._faces = b.array("mesh.faces", len(f), wp.vec3i)
        self._faces.assign(f)
        self._clock = StageClock(self._device)
        self._stream = wp.Stream(self._device) if self._device.is_cuda else None
        self._beside = SideStream(self._device)  # the BVH's refit runs on it, beside the octree's build
        # the frame's counts, copied to the host at its end (pinned, so the copy can be part of a graph)
        self._report = wp.zeros(_REPORT_LENGTH, dtype=wp.int32, device="cpu", pinned=self._device.is_cuda)
        self._report_on_device = b.array("frame.report", _REPORT_LENGTH, wp.int32)  # gathered there, one copy back
        self._keep_queued = False  # whether the frame queued the keeping of its corners on the device (queue_keep)
        self._staging = wp.empty(vertex_count, dtype=wp.vec3, device="cpu", pinned=self._device.is_cuda)
        # what takes a staged frame to local coordinates: centre (3) and scale, written on the host beside the
        # vertices (_stage_frame) and read on the device, so the frame's upload is part of its graph
        self._to_local = HostStaged(b.array("frame.to_local", 4, wp.float32))
        self._failed_update: str | None = None  # why the last update failed after its input was checked
        self._planned = False  # whether the next frame may be planned (from an estimate, or a frame's counts)
        self._estimated = False  # whether the next frame's plan is an estimate (the first frame's, from its area)
        self._fit_buffers = False  # whether the next frame sizes the buffers anew (after an estimated frame)
        # frames in a row whose counts needed far less than the plan, and the largest of their counts (_watch_plan)
        self._oversized_frames, self._oversized_peak = 0, None
        self._graph = None  # (key, graph, stage names, keep queued) of the captured planned frame
        self._graph_candidate = None  # key of the last planned frame run eagerly
        self.use_graphs = True
        # the fans that make an open mesh's winding numbers exact where they come near 1/2 (None: a rim too long)
        rim = rim_fans(f, topology=self._topology) if self._sign != "none" else np.zeros((0, 3), np.int32)
        self._rim_fans = None if rim is None else len(rim)
        if rim is None and self._sign == "winding":
            log.warning("the surface's rim (its faces' edges that no other face runs the other way) needs more than %d "
                        "fans, so winding numbers near 1/2, about its openings, keep the walk's estimate and such "
                        "points may read the wrong side. A mesh whose faces share no vertex ids (a triangle soup, as "
                        "STL stores) has every edge on its rim: merge its coincident vertices first", RIM_LIMIT)
        # the rim's edges (welded: a seam is no rim), whose leaves winding-signed ADF queries answer exactly
        self._rim_edges = None
        if self._sign == "winding" and len(self._topology.rim_edges):
            edges = rim_edge_vertices(self._topology, f)
            self._rim_edges = b.array("sign.rim_edges", len(edges), wp.vec2i)
            self._rim_edges.assign(edges)
        self._bvh = Bvh(len(f), with_moments=self._sign != "none", buffers=b, shape=shape, rim=rim)
        self._octree = Octree(self._depth, self._refine, self._halo, b)
        self._octree.surface_area = area
        self._normals = Pseudonormals(self._sign, self._topology, self._faces, b)
        self._corners = CornerField(b, self._octree.scratch)
        self._points = PointQuery(b)
        self._slice_cells = SliceCells(b)
        # the first frame is planned from the surface's area where the octree can estimate it, and measured
        # again only if it outgrew that plan
        self._planned = self._estimated = self._octree.plan_first_frame(len(f), self._domain.local_side)
        self._apply(local, extent, domain_moved=True)

    # -- public API -----------------------------------------------------------------------------------
    @_on_device
    def update(self, vertices) -> int:
        """Replace the vertex positions (same count and topology) and rebuild the field; returns the frame.
        A rigid frame (rigid="auto") keeps the field and its pose from it instead.

        Raises InvalidInputError (and keeps the last good frame) on a wrong shape or non-finite value.
        """
        v = as_vertices(vertices, expected_count=self._vertex_count)
        # a frame due to link the tree again is rebuilt, rigid or not: the exact queries walk the tree too
        if self._rigid_test is not None and self._failed_update is None and not self._relink_due:
            wall = time.perf_counter()
            pose = self._rigid_test.pose(self._reference, v, self._rigid_tolerance)
            if pose is not None:
                return self._take_rigid_frame(v, pose, wall)
        self._rebuild(v)
        self._frame += 1
        self._counters.updates += 1
        return self._frame

    def _take_rigid_frame(self, v: np.ndarray, pose: Pose, wall: float) -> int:
        """Keep the field of the reference frame for frame v, which is the reference moved by `pose`."""
        identity = bool(np.array_equal(pose.rotation, np.eye(3)) and not pose.translation.any())
        self._pose = None if identity else pose
        if not identity:  # a copy: the caller may write into theirs
            self._posed_vertices = _held_copy(self._posed_vertices, v)
        self._frame += 1
        self._counters.updates += 1
        self._counters.rigid_frames += 1
        self._rigid_run += 1
        if self._rigid_run == self._scratch_kept_frames and self._give_back_scratch():
            # a run this long is a rigid body's: what only a rebuild uses is given back until one comes
            self._counters.scratch_given_back += 1
        self._counters.last_update_wall_ms = (time.perf_counter() - wall) * 1e3
        return self._frame

    def _give_back_scratch(self) -> bool:
        """Free what only a rebuild uses: the octree's frame scratch and what only a BVH build uses (which a body
        registered and then only moved rigidly kept: 4.4 MB for the bunny); whether there was any. The captured
        frame lays its arrays over the scratch, so it goes too, and the next rebuild runs eagerly before it is
        captured again."""
        self._graph = self._graph_candidate = None
        wp.synchronize_device(self._device)  # no queued frame still reads them
        scratch = self._octree.scratch.give_back()
        return self._bvh.give_back_build() or scratch

    @_on_device
    def trim(self) -> int:
        """Give back the memory that only the next frame, query or slice would use; the bytes freed.

        For an object that will sit idle for a while (a static obstacle, a body between takes): the field, the
        mesh and the BVH's shape stay, so queries answer as before, bit for bit. Freed are the octree's frame scratch (with
        the captured frame), what only a BVH build uses, what a refit writes in full (the BVH's boxes, packed
        triangles and winding moments: the next query or frame refits them first, to the same bits), last frame's
        nearest faces (the next frame then searches without them, as a first frame does: the same answers, at a
        first frame's cost) and the buffers of the largest query and slice so far (on CUDA, their pinned host twins
        too). Each comes back when it is next needed. The bunny at depth 7 holds 32.7 MiB, 13.3 after a trim (a query of a million points with every
        output adds 44 MiB of buffers until one)."""
        before = self._buffers.nbytes()
        self._give_back_scratch()
        self._bvh.give_back_geometry()  # with its kept views, which hold the arrays
        self._corners.forget_frame()
        for prefix in ("query.", "slice."):
            self._buffers.release(prefix)
        self._points.give_back()
        freed = before - self._buffers.nbytes()
        if freed > 0:
            self._counters.trims += 1
        return freed

    def _rebuild(self, v: np.ndarray) -> None:
        """Rebuild the field for checked vertices v, which become the reference frame of later rigid ones."""
        lo, hi = self._bounds(v)
        moved = self._failed_update is not None or not self._domain.holds(lo, hi)
        if moved:
            self._domain = _Domain.fit(lo, hi, previous=self._domain)
            self._counters.domain_moves += 1
        relink = self._relink_due and not moved  # a frame that moves the domain links the tree anyway
        # float32 frames are recentred on the device (the same float32 subtraction, without numpy's slow
        # (N, 3) broadcast); float64 ones on the host in float64, which keeps the precision far from the origin
        recentre = v.dtype == np.float32 and self._domain.recentres_float32
        try:
            local, extent = v if recentre else self._domain.to_local(v), float(np.max(hi - lo)) * self._domain.scale
            self._apply(local, extent, domain_moved=moved or relink, recentre=recentre)
            if self._tree_fit == TREE_MISFITS and self._counters.winding_walks_cut > 0:
                # the tree misfits this frame so badly that its winding walks met their budget (a calm frame on a tree
                # linked on a violent one): its sides may be estimates, so it runs again on a tree linked on itself.
                # A soup's own walks meet the budget on any tree, and its leaves lie no farther apart than its large
                # triangles: it is not run again, and the next frame links the tree. The frame's wall time is both
                # runs'; its stage times are the second's.
                first_wall_ms = self._counters.last_update_wall_ms
                self._apply(local, extent, domain_moved=True, recentre=recentre)
                self._counters.last_update_wall_ms += first_wall_ms
                relink = True
        except BaseException as error:
            # Valid input that failed on the way (out of device memory, a device fault): the buffers may hold
            # part of this frame and part of the last, so the object answers nothing until a frame goes
            # through, and that frame is rebuilt in full, measured, without a graph.
            self._failed_update = f"{type(error).__name__}: {error}"
            self._planned, self._graph, self._graph_candidate = False, None, None
            self._pose = None
            raise
        self._failed_update = None
        self._pose = None
        self._rigid_run = 0
        self._counters.bvh_relinks += relink
        self._keep_reference(v, lo, hi)

    def _keep_reference(self, v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        """Keep a rebuilt frame (a copy: the caller may write into theirs) for the test of later rigid frames."""
        if self._rigid_test is not None:
            self._reference = _held_copy(self._reference, v)
            self._rigid_tolerance = RIGID_TOLERANCE * float(np.linalg.norm(hi - lo))

    def _in_place(self) -> None:
        """Rebuild the field where the current frame is, if it is a rigid frame's (slices and the corner and cell
        lists are in the world's axes); the frame's number stays."""
        if self._pose is not None:
            self._rebuild(self._posed_vertices)
            self._counters.rigid_rebuilds += 1

    @_on_device
    def query(
        self,
        points,
        *,
        mode: QueryMode = "adf",
        outputs: tuple[QueryOutput, ...] | list[QueryOutput] = ("distance",),
    ) -> QueryResult:
        """Distances (and what else `outputs` names) at (P, 3) points, for the current frame.

        mode "adf" interpolates the octree's corners trilinearly (exact outside the domain); "exact" runs a
        BVH closest-point search bounded by the faces recorded at the point's cell corners. Batches larger
        than QUERY_CHUNK points are processed in chunks, so device memory stays bounded.
        """
        self._check_field()
        mode = check_choice(mode, "mode", QUERY_MODES)
        names = check_outputs(outputs)
        p = as_points(points)
        start_time = time.perf_counter()
        self._bvh.query_cuts.zero_()  # the walks this query cuts (stats()["last_query_walks_cut"])
        result = self._answer(p, mode, names, self._pose, cut_slot=1)
        self._counters.queries += 1
        self._counters.query_points += len(p)
        self._counters.last_query_ms = (time.perf_counter() - start_time) * 1e3
        return result

    def _answer(self, p: np.ndarray, mode: QueryMode, names: tuple[QueryOutput, ...], pose: Pose | None = None,
                cut_slot: int = 0) -> QueryResult:
        """The outputs `names` at checked points p: a query's work, which a slice shares (uncounted). With a rigid
        frame's pose, the points are turned into the field's frame on the device, and its closest points and
        normals turned back out on the host (distances and faces are the same in both). Winding walks cut short
        count in `winding_cuts[cut_slot]` (a query's in slot 1; a slice's in the frame's slot, after its report)."""
        self._bvh.hold_geometry(self._vertices, self._faces)  # given back by a trim: refitted to this frame again
        count = len(p)
        result = QueryResult(frame=self._frame)
        shapes = {"distance": ((count,), np.float32), "closest_point": ((count, 3), np.float32),
                  "normal": ((count, 3), np.float32), "face": ((count,), np.int32)}
        # beyond a band there is no closest point; the faces (-1 there) say where, also when not asked for
        computed = names
        if self._band is not None and "closest_point" in names and "face" not in names:
            computed = (*names, "face")
        arrays = {name: np.empty(*shapes[name]) for name in computed}
        bits = 0
        for name in computed:
            bits |= OUTPUT_BITS[name]
        domain = self._domain
        # the cube where the points are measured from: the field's, or where the pose has carried it
        placed, turn, shift = (domain, None, None) if pose is None else _placed(domain, pose)
        tree, bvh, sign = self._query_views(cut_slot)
        if mode == "adf" and bits & (OUT_CLOSEST | OUT_NORMAL):
            self._mark_medial_leaves(tree, bvh)
        if mode == "adf":
            self._mark_rim_leaves(tree)
        band = domain.local_band(self._band)
        # float32 points are recentred on the device (the same float32 arithmetic); float64 ones on the host
        # in float64, which keeps the precision of points far from the origin
        on_device = p.dtype == np.float32 and placed.recentres_float32
        far, beyond = _pull_far_points(p, placed)
        if far is not None:
            p, on_device = far, False  # already local
        offset = placed.centre.astype(np.float32) if on_device else np.zeros(3, np.float32)
        scale = domain.scale if on_device else 1.0
        for start in range(0, count, QUERY_CHUNK):
            chunk = p[start : start + QUERY_CHUNK]
            self._points.run(chunk if on_device or far is not None else placed.to_local(chunk), offset, scale,
                             exact=mode == "exact", outputs=bits, octree=tree,
                             corner_value=self._corners.value, corner_leaf=self._corners.leaf, bvh=bvh, sign=sign,
                             side=domain.local_side, band=band, results=arrays, start=start, turn=turn, shift=shift)
        if "distance" in arrays:
            distance = arrays["distance"]
            _to_world_units(distance, domain.scale)
            if beyond is not None:
                rows, extra = beyond
                moved = distance[rows] + extra
                distance[rows] = moved if band is None else np.minimum(moved, domain.band_in_force(self._band))
        if "closest_point" in arrays:
            closest = arrays["closest_point"]
            _to_world_units(closest, domain.scale)
            if pose is None:  # column by column: numpy broadcasts a row of 3 over (N, 3) 5 times slower
                for axis, coordinate in enumerate(domain.centre.astype(np.float32)):
                    closest[:, axis] += coordinate
            else:  # from the field's centre, turned with the frame, to where the frame has that centre
                closest[...] = pose.vectors_to_world(closest) + (pose.rotation @ domain.centre + pose.translation)
            if self._band is not None:
                closest[arrays["face"] < 0] = 0.0
        if "normal" in arrays and pose is not None:
            arrays["normal"] = pose.vectors_to_world(arrays["normal"])
        for name in names:
            setattr(result, name, arrays[name])
        return result

    @_on_device
    def slice(
        self,
        axis: Literal["x", "y", "z"] | int,
        position: float,
        *,
        resolution: int | tuple[int, int] = 256,
        max_level: int | None = None,
    ) -> Slice:
        """The field on the plane {axis = position} over the domain's extent, and the octree cells it crosses.

        resolution: columns x rows of the distance grid (an int for a square grid), each 1..2048.
        max_level: leave out cells deeper than this level (None: all, down to the finest).
        """
        self._check_field()
        start_time = time.perf_counter()
        axis_index = check_axis(axis)
        position = check_finite_number(position, "position")
        if abs(position) > MAX_COORDINATE:
            raise InvalidInputError(f"position must lie within +-{MAX_COORDINATE:g}, got {position:g}")
        rows, cols = check_resolution(resolution)
        max_level = self._depth if max_level is None else check_level(max_level, self._depth)
        self._in_place()
        centre, half = self._domain.centre, self._domain.side / 2.0
        u_axis, v_axis = [a for a in range(3) if a != axis_index]
        u_range = (float(centre[u_axis] - half), float(centre[u_axis] + half))
        v_range = (float(centre[v_axis] - half), float(centre[v_axis] + half))
        grid = plane_grid(axis_index, position, u_range, v_range, rows, cols)
        distance = self._answer(as_points(grid), "adf", ("distance",)).distance.reshape(rows, cols)
        o = self._octree
        with wp.ScopedDevice(self._device):
            lower, upper, level, leaf, empty = self._slice_cells.cells(
                o.node_keys, o.child_mask, o.internal_count, o.level_counts, self._depth, axis_index,
                float((position - centre[axis_index]) * self._domain.scale), self._domain.local_side, max_level,
            )
        for corners in (lower, upper):
            _to_world_units(corners, self._domain.scale)
            corners += centre.astype(np.float32)
        # counted apart from queries: a slice counted as one, with its grid's points (sixteenth outside check)
        self._counters.slices += 1
        self._counters.last_slice_ms = (time.perf_counter() - start_time) * 1e3
        return Slice(axis=AXES[axis_index], position=position, distance=distance, u_range=u_range, v_range=v_range,
                     cell_lower=lower, cell_upper=upper, cell_level=level, cell_is_leaf=leaf, cell_is_empty=empty,
                     frame=self._frame)

    @property
    def frame(self) -> int:
        return self._frame

    def _domain_centre(self) -> np.ndarray:
        centre = self._domain.centre
        return centre if self._pose is None else self._pose.rotation @ centre + self._pose.translation

    def _check_field(self) -> None:
        if self._failed_update is not None:
            raise FieldUnavailableError(
                f"the field of frame {self._frame} is gone: the next update failed ({self._failed_update}); "
                "update the object again, which rebuilds it in full"
            )

    @property
    def vertex_count(self) -> int:
        return self._vertex_count

    @property
    def face_count(self) -> int:
        return self._face_count

    @property
    def device(self) -> str:
        return str(self._device)

    @_on_device
    def info(self) -> dict:
        """Resolved options and facts about the mesh (JSON-serialisable)."""
        return {
            "vertices": self._vertex_count,
            "faces": self._face_count,
            "device": self.device,
            "depth": self._depth,
            "sign": self._sign,
            "sign_requested": self._sign_requested,
            "sign_this_frame": self._normals.frame_method,
            "band": self._band,
            # the band the searches clamp at: the one asked for, or MIN_BAND of a domain that has grown since
            "band_in_force": self._domain.band_in_force(self._band),
            "coherence": self._coherence,
            "refine": self._refine,
            "halo": self._halo,
            "region": None if self._region is None else self._region.tolist(),
            "bvh": self._bvh_shape,
            "bvh_requested": self._bvh_requested,
            "failed_update": self._failed_update,
            "orientation_flipped": self._flipped,
            "parts_face_both_ways": self._parts_disagree,
            # found in the first frame (and every frame then signed by winding numbers), or in this one
            "parts_overlap": self._parts_overlap or self._normals.frame_parts_overlap,
            # this frame pulled apart vertices the first frame's weld joined along an edge: signed by winding
            "seams_torn": self._normals.frame_seams_torn,
            "topology": self._topology.summary(),
            # fans closing the faces' boundary, which make winding numbers near 1/2 exact (0: none needed or no
            # sign; None: a rim longer than RIM_LIMIT, left to the walk)
            "rim_fans": self._rim_fans,
            # edges of the welded rim, whose leaves a winding-signed field's ADF queries answer exactly (0: none)
            "rim_edges": 0 if self._rim_edges is None else len(self._rim_edges),
            # the cube the octree covers: where the current frame has it (turned by the pose's rotation, if any)
            "domain": {"centre": self._domain_centre().tolist(), "side": self._domain.side,
                       "finest_cell": self._domain.side / (1 << self._depth)},
            "rigid": self._rigid_mode if self._rigid_test is not None else "off",
            # the current frame's rigid motion from the frame the field was built for (None: built for this one)
            "pose": None if self._pose is None else self._pose.as_dict(),
            "frame": self._frame,
        }

    @_on_device
    def stats(self) -> dict:
        """Counts, per-stage times (ms) of the last build or update, and device bytes (JSON-serialisable)."""
        o = self._octree
        internal = o.internal_count
        leaves = 8 * internal - (o.node_count - 1) + int(o.level_counts[-1])
        c = self._counters
        return {
            "frame": self._frame,
            "device": self.device,
            "counts": {
                "vertices": self._vertex_count,
                "faces": self._face_count,
                "surface_cells": o.surface_cell_count,
                "octree_nodes": o.node_count,
                "nodes_per_level": [int(x) for x in o.level_counts],
                "internal_nodes": internal,
                "leaves": leaves,
                "corner_candidates": 8 * leaves,
                "unique_corners": o.corner_count,
                "coherent_frame": self._corners.coherent,
                # visits after which a corner's search was shared out over BVH subtrees (0: never)
                "corner_search_budget": self._corners.search_budget,
            },
            "times_ms": self._clock.times_ms(),
            "update_wall_ms": round(c.last_update_wall_ms, 4),
            # the host's time making the BVH's shape at registration (bvh="sah"; None for "morton", linked on the device)
            "bvh_shape_ms": None if self._shape_ms is None else round(self._shape_ms, 3),
            "last_query_ms": round(c.last_query_ms, 4),
            "updates": c.updates,
            "domain_moves": c.domain_moves,
            "replans": c.replans,
            "measured_frames": c.measured_frames,
            "graph_captures": c.graph_captures,
            "rigid_frames": c.rigid_frames,
            "rigid_rebuilds": c.rigid_rebuilds,
            "plans_given_back": c.plans_given_back,
            "scratch_given_back": c.scratch_given_back,
            "trims": c.trims,
            "winding_walks_cut": c.winding_walks_cut,
            # the last query's winding walks cut short (its signs there are estimates): read from the device here
            "last_query_walks_cut": int(self._bvh.winding_cuts.numpy()[1]),
            "bvh_relinks": c.bvh_relinks,
            "bvh_leaf_spread": round(self._tree_spread, 3),
            "queries": c.queries,
            "query_points": c.query_points,
            "slices": c.slices,
            "last_slice_ms": round(c.last_slice_ms, 4),
            "device_bytes": self._buffers.nbytes(),
            "memory_bytes": self._buffers.nbytes_by_role(),
        }

    def _mark_medial_leaves(self, tree, bvh) -> None:
        """Mark the leaves near the surface whose corners' nearest points lie in directions far apart
        (mark_medial_leaves), where an ADF normal comes from p's nearest face: once a frame, for its first ADF
        query that asks for normals or closest points, so that frames queried for distances alone pay nothing."""
        if self._medial_marked:
            return
        o = self._octree
        wp.launch(mark_medial_leaves, dim=o.internal_capacity,
                  inputs=[o.node_keys, o.totals, o.internal_capacity, tree, self._corners.value, self._corners.leaf,
                          bvh, 1.0 / self._domain.local_side, 0 if self._sign == "none" else 1],
                  outputs=[o.child_mask], device=self._device)
        self._medial_marked = True

    def _mark_rim_leaves(self, tree) -> None:
        """Mark the leaves a winding-signed mesh's rim crosses (mark_rim_leaves), whose ADF answers are exact: once
        a frame, for its first ADF query; nothing where there is no rim or no winding sign."""
        if self._rim_marked or self._rim_edges is None:
            return
        wp.launch(mark_rim_leaves, dim=len(self._rim_edges), inputs=[self._vertices, self._rim_edges, tree],
                  outputs=[self._octree.child_mask], device=self._device)
        self._rim_marked = True

    # -- the pipeline ---------------------------------------------------------------------------------
    def _apply(self, local_vertices: np.ndarray, extent: float, *, domain_moved: bool, recentre: bool = False) -> None:
        """Upload a frame and rebuild the field: refit (or rebuild, when the domain moved), sign data,
        octree, corners, corner distances.

        Every frame is planned where it can be, also when the domain moved (the BVH is then rebuilt): its
        buffers keep last frame's sizes with headroom (the first frame's are estimated from the surface's
        area) and nothing is read back until the end, when the frame's counts are checked against them; a
        frame that outgrew them is run again, measured.
        On CUDA a planned frame is replayed from a CUDA graph, captured from an identical planned frame
        (same sizes, domain and settings), so it costs one launch. Each object runs its frames on a stream
        of its own: the graph holds the sort's scratch memory, which Warp keeps per stream and another
        object's larger sort would otherwise reallocate.
        """
        wall = time.perf_counter()
        self._bvh.hold_geometry(self._vertices, self._faces)  # given back by a trim: this frame refits it anyway
        if not domain_moved and self._bvh.give_back_build():
            self._graph = None  # a graph that rebuilt the BVH holds what was given back
        self._medial_marked = False  # the leaves the medial surface crosses, marked on demand (query)
        self._rim_marked = False  # and those the rim crosses
        clock = self._clock
        clock.reset()
        stream = wp.ScopedStream(self._stream) if self._stream is not None else contextlib.nullcontext()
        # the frame after one planned from an estimate gives back what the estimate held beyond its own plan
        fitting = self._buffers.fit() if self._fit_buffers else contextlib.nullcontext()
        self._fit_buffers = False
        with wp.ScopedDevice(self._device), stream, fitting, clock.stage("total"):
            self._stage_frame(local_vertices, recentre)
            self._normals.stage_extent(extent)
            self._corners.stage_lattice(self._domain, self._depth)
            fits = self._planned and self._planned_frame(domain_moved)
            if not fits:
                self._graph = None
                self._pipeline(measure=True, domain_moved=domain_moved)
                self._counters.measured_frames += 1
                self._take_report()
                self._planned = True
            self._corners.keep_frame(self._report_on_device, self._fits_at, queued=self._keep_queued)
        self._watch_plan()
        # made again where this frame replaced an array they hold (below), and the kept query launch let go of
        # where it holds another
        self._points.let_go_unless((*self._query_views(cut_slot=1), self._corners.value, self._corners.leaf))
        self._counters.last_update_wall_ms = (time.perf_counter() - wall) * 1e3

    def _query_views(self, cut_slot: int) -> tuple:
        """The octree, BVH and sign views a query's kernel takes. They are kept while their arrays stay the same
        (`KeptViews`); each frame asks for them too, so that an array it replaced is freed then rather than at the
        next query (about 8 us a frame where nothing was replaced)."""
        return (self._octree.view(self._domain.origin, self._domain.local_side), self._bvh.view(cut_slot),
                self._normals.view())

    @property
    def _relink_due(self) -> bool:
        """Whether the next frame links the BVH again. A tree linked on Morton codes is refitted to later
        frames while the domain holds them; once its leaves lie RELINK_SPREAD times as far apart for their size as
        in the frame it was linked on (a violent frame's soup, then the calm mesh: every walk then runs long), the
        next frame links it on its own codes. The device decides it (`tree_fit`, in the frame's report), from the
        sums it keeps of the linking frame; a frame that linked the tree fits it, and a tree that is never measured
        (the SAH's shape, kept) always fits."""
        return self._tree_fit >= TREE_DUE

    def _watch_plan(self) -> None:
        """After a frame: give back a plan that has long held far more than the frames need. Once each of
        _PLAN_GIVEN_BACK_AFTER frames in a row needed less than 1/_PLAN_GIVEN_BACK_OVER of it, later frames are
        planned for the largest of those frames' counts, and the next frame sizes the buffers anew (`fit`, as after
        a first frame planned from an estimate). A frame that then outgrows the plan is measured, as any is."""
        o = self._octree
        counts = o.counts()
        if o.plan_excess(counts) < _PLAN_GIVEN_BACK_OVER:
            self._oversized_frames, self._oversized_peak = 0, None
            return
        peak = counts if self._oversized_peak is None else tuple(map(max, self._oversized_peak, counts))
        self._oversized_frames, self._oversized_peak = self._oversized_frames + 1, peak
        if self._oversized_frames >= _PLAN_GIVEN_BACK_AFTER:
            o.replan_from_counts(peak)
            self._fit_buffers = True
            self._counters.plans_given_back += 1
            self._oversized_frames, self._oversized_peak = 0, None

    def _stage_frame(self, vertices: np.ndarray, recentre: bool) -> None:
        """Write the frame where its upload (_upload_frame) reads it: the vertices into a pinned buffer, so that the
        copy runs asynchronously (a pageable one waits for it), with the centre and scale that take them to local
        coordinates (0 and 1 for a frame already local, which leaves it bit for bit as it came)."""
        self._staging.numpy()[:] = vertices
        to_local = self._to_local.host()
        to_local[:3] = self._domain.centre if recentre else 0.0
        to_local[3] = self._domain.scale if recentre else 1.0

    def _upload_frame(self) -> None:
        """Queue the staged frame's copy to the device and its move to local coordinates: within the frame, so a
        replayed frame is one launch from the host."""
        wp.copy(self._vertices, self._staging)
        self._bvh.winding_cuts[0:1].zero_()  # this frame's count, for its report (the last query's is kept)
        self._to_local.upload()
        wp.launch(_move_to_local, dim=self._vertex_count, inputs=[self._vertices, self._to_local.array])

    def _planned_frame(self, domain_moved: bool) -> bool:
        """Run a planned frame; whether it fitted its plan (else it is counted as a replan)."""
        self._run_planned(domain_moved)
        fits = self._take_report()
        estimated, self._estimated = self._estimated, False
        if fits and estimated:
            # Later frames are planned for what this one found, and the next gives back what the estimate held
            # beyond that. An estimate far too large (a surface lying on copies of itself) is given back at once:
            # the frame is run again at the sizes it found.
            if self._octree.replan_from_counts() <= _ESTIMATE_KEPT:
                self._fit_buffers = True
            else:
                with self._buffers.fit():
                    self._run_planned(domain_moved)
                    fits = self._take_report()
        if not fits:
            self._counters.replans += 1
        return fits

    def _pipeline(self, *, measure: bool, domain_moved: bool = False) -> None:
        """Queue one frame's kernels (measuring reads sizes back on the way) and its report."""
        clock = self._clock
        origin, side = self._domain.origin, self._domain.local_side
        with clock.stage("upload"):  # before the fork: the work beside reads the vertices and the extent
            self._upload_frame()
            self._normals.upload_extent()
        # the BVH and the sign data need only the vertices, as does the octree: on CUDA they run beside it
        beside = self._beside.fork()
        with wp.ScopedStream(beside, sync_enter=False) if beside is not None else contextlib.nullcontext():
            if domain_moved:
                with clock.stage("bvh_build"):
                    self._bvh.build(self._vertices, self._faces, origin, side)
            with clock.stage("refit"):
                self._bvh.refit(self._vertices, self._faces)
                if self._bvh.shape is None:  # a tree linked on Morton codes, which a frame far from its own misfits
                    self._bvh.measure_spread(side, linked=domain_moved)
            with clock.stage("normals"):
                self._normals.update(self._vertices)
        o = self._octree
        if self._region is not None:  # in local coordinates, which follow the domain
            o.set_region(self._domain.to_local_float64(self._region), origin, side)
        # a planned frame reserves the scratch for the corners' own arrays too, which are laid over it once the
        # octree is built
        corners = () if measure else (self._corners.scratch_layout(o.planned_corner_capacity(), o.corner_count,
                                                                   self._bvh.internal_count, self._normals.code),)
        o.build(self._vertices, self._faces, self._face_count, origin, side, clock, measure=measure, reserve=corners)
        self._beside.join(beside)
        with clock.stage("distances"):
            self._corners.compute(o.corner_keys, o.corner_set.view.count, o.corner_capacity, o.corner_count,
                                  self._bvh.view(), self._bvh.cut, self._normals.view(), self._domain,
                                  self._depth, self._band, coherent=self._coherence,
                                  choose_sign=functools.partial(self._normals.choose_frame_method, self._vertices,
                                                                self._bvh.view()))
        self._queue_report()

    def _run_planned(self, domain_moved: bool) -> None:
        """A planned frame: eagerly on the CPU or the first time with these sizes (a frame that moved the domain,
        which rebuilds the BVH, has sizes of its own); else from a graph."""
        if not (self._device.is_cuda and self.use_graphs):
            self._pipeline(measure=False, domain_moved=domain_moved)
            return
        split = self._corners.planned_split(self._octree.corner_count, self._bvh.internal_count)
        key = self._plan_key(split, domain_moved)
        # the cuts a frame's searches read are worked out outside its graph and kept until the next BVH build, so
        # after one (a frame that moved the domain) they are worked out again, for the graph and the capture alike
        self._corners.make_cuts(split, self._corners.far_cells_for(self._normals.code), self._bvh.cut)
        if self._graph is not None and self._graph[0] == key:
            _, graph, stages, self._keep_queued = self._graph
            wp.capture_launch(graph)
            self._clock.replayed(stages)
            return
        if self._graph_candidate != key:
            # run it once eagerly: any buffer (and the sort's scratch) that must grow does so outside a capture
            self._graph_candidate = key
            self._graph = None
            self._pipeline(measure=False, domain_moved=domain_moved)
            return
        stages_before = list(self._clock.recorded)
        try:
            wp.capture_begin(self._device, stream=self._stream, force_module_load=False)
            try:
                self._pipeline(measure=False, domain_moved=domain_moved)
            finally:
                graph = wp.capture_end(self._device, stream=self._stream)
        except Exception as error:  # a driver or Warp build that cannot capture: run kernel by kernel
            log.warning("CUDA graph capture failed on %s (%s); planned frames run kernel by kernel", self._device, error)
            self.use_graphs = False
            self._pipeline(measure=False, domain_moved=domain_moved)
            return
        stages = [name for name in self._clock.recorded if name not in stages_before]
        self._graph = (key, graph, stages, self._keep_queued)
        self._counters.graph_captures += 1
        wp.capture_launch(graph)

    def _plan_key(self, split, domain_moved: bool) -> tuple:
        """Everything a planned frame's launches take by value; a graph is replayed only for an equal key. The
        kernels work in local coordinates, which the side alone sets (the centre is taken off on the way up), so a
        frame that moves the domain without changing its side replays the graph of the last such frame."""
        o, c = self._octree, self._corners
        region = None if self._region is None else tuple(self._domain.to_local_float64(self._region).ravel())
        return (
            o.cell_set.planned, o.surface_planned, o.node_capacity, o.internal_capacity, o.corner_set.planned,
            self._domain.side, region, domain_moved, c.coherence_key(), (split.budget, split.levels, split.groups),
            c.far_cells_for(self._normals.code),
        )

    def _queue_report(self) -> None:
        """Gather the frame's counts on the device, with whether each fits its capacity, and queue the keeping of
        the frame (which takes effect only if they all do) and one copy of the counts to the host. The layout
        (`_take_report`): the sizes, the sign's frame method, the levels' first nodes, whether parts overlap, whether
        seams tore, the surface's own cells, whether it all fitted, the winding walks cut short, the leaf spread, how the
        tree fits the frame (`tree_fit`)."""
        sizes = self._octree.report()
        assert len(sizes) == _REPORT_SIZES
        (a0, i0, c0), (a1, i1, c1), (a2, i2, c2), (a3, i3, c3) = sizes
        n = self._normals
        wp.launch(_gather_report, dim=1,
                  inputs=[a0, i0, c0, a1, i1, c1, a2, i2, c2, a3, i3, c3, n.winding_frame, self._octree.level_starts,
                          self._depth + 1, n.parts_overlap, n.seams_torn, self._octree.surface_count,
                          self._bvh.winding_cuts, self._bvh.leaf_spread],
                  outputs=[self._report_on_device], device=self._device)
        self._keep_queued = self._corners.queue_keep(self._report_on_device, self._fits_at)
        wp.copy(self._report, self._report_on_device, count=self._fits_at + 4)

    @property
    def _fits_at(self) -> int:
        return _REPORT_SIZES + 5 + self._depth

    def _take_report(self) -> bool:
        """Wait for the frame and read its counts; whether every one fitted its capacity (the device's verdict,
        which the keeping of the frame took too)."""
        if self._device.is_cuda:
            wp.synchronize_stream(self._stream)
        report = self._report.numpy()
        if report[self._fits_at] != 1:
            return False
        k = _REPORT_SIZES
        counts = [int(x) for x in report[:k]]
        self._octree.take_counts(counts, report[k + 1 : k + 2 + self._depth], int(report[k + 4 + self._depth]))
        self._normals.set_frame_method(int(report[k]), int(report[k + 2 + self._depth]), int(report[k + 3 + self._depth]))
        self._counters.winding_walks_cut = int(report[self._fits_at + 1])
        self._tree_spread = int(report[self._fits_at + 2]) / SPREAD_UNIT
        self._tree_fit = int(report[self._fits_at + 3])
        return True

    # -- for tests and tools --------------------------------------------------------------------------
    @_on_device
    def corner_samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(positions (C, 3) float64 in world coordinates, signed distances (C,), nearest faces (C,)); with a band,
        a corner clamped at it has no face within it: -1, as a query there answers."""
        self._in_place()
        keys = self._octree.corner_keys.numpy()[: self._octree.corner_count]
        lattice = _decode_morton(keys)
        cell = self._domain.side / (1 << self._depth)
        positions = self._domain.centre + (-self._domain.side / 2.0 + lattice * cell)
        n = self._octree.corner_count
        values = self._corners.value.numpy()[:n].copy()  # on the CPU, numpy() is a view of the buffer
        faces = self._bvh.leaf_faces()[self._corners.leaf.numpy()[:n]]
        band = self._domain.local_band(self._band)
        if band is not None:
            # the kernels' test (float32 values against the float32 band): the face kept there is only the search's
            # seed, last frame's or a spatial one, which the next frame and exact queries start from
            faces[np.abs(values) >= np.float32(band)] = -1
        _to_world_units(values, self._domain.scale)
        return positions, values, faces

    @_on_device
    def octree_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """(levels (K,), integer cell coordinates (K, 3) at each node's level) of every octree node."""
        self._in_place()
        keys = self._octree.node_keys.numpy()[: self._octree.node_count]
        levels = (keys >> 32).astype(np.int64)
        return levels, _decode_morton(keys & 0xFFFFFFFF).astype(np.int64)


# The frame's report: four sizes, the sign's frame method, up to MAX_DEPTH + 1 levels' first nodes, three flags, the
# winding walks cut short, the BVH's leaf spread (Bvh.measure_spread: gaps over sizes) in 1 / SPREAD_UNIT, the tree's
# fit (`tree_fit`)
_REPORT_SIZES = 4
_REPORT_LENGTH = 32


@wp.kernel(enable_backward=False)
def _gather_report(a0: wp.array(dtype=wp.int32), i0: int, c0: int, a1: wp.array(dtype=wp.int32), i1: int, c1: int,
                   a2: wp.array(dtype=wp.int32), i2: int, c2: int, a3: wp.array(dtype=wp.int32), i3: int, c3: int,
                   winding_frame: wp.array(dtype=wp.int32), level_starts: wp.array(dtype=wp.int32), levels: int,
                   parts_overlap: wp.array(dtype=wp.int32), seams_torn: wp.array(dtype=wp.int32),
                   surface_count: wp.array(dtype=wp.int32), winding_cuts: wp.array(dtype=wp.int32),
                   leaf_spread: wp.array(dtype=wp.int64), report: wp.array(dtype=wp.int32)):
    """One thread writes the frame's report (`DistanceField._queue_report`'s layout)."""
    report[0] = a0[i0]
    report[1] = a1[i1]
    report[2] = a2[i2]
    report[3] = a3[i3]
    report[4] = winding_frame[0]
    for level in range(levels):
        report[5 + level] = level_starts[level]
    report[5 + levels] = parts_overlap[0]
    report[6 + levels] = seams_torn[0]
    report[7 + levels] = surface_count[0]
    fits = a0[i0] <= c0 and a1[i1] <= c1 and a2[i2] <= c2 and a3[i3] <= c3
    report[8 + levels] = wp.where(fits, 1, 0)
    report[9 + levels] = winding_cuts[0]
    report[10 + levels] = spread_units(leaf_spread[0], leaf_spread[1])
    report[11 + levels] = tree_fit(leaf_spread)


@wp.kernel(enable_backward=False)
def _move_to_local(vertices: wp.array(dtype=wp.vec3), to_local: wp.array(dtype=wp.float32)):
    """Positions to local coordinates in place: less the centre, times the scale (to_local, as _stage_frame wrote it).
    A frame that came local has centre 0 and scale 1, which leave every finite coordinate as it is."""
    i = wp.tid()
    vertices[i] = (vertices[i] - wp.vec3(to_local[0], to_local[1], to_local[2])) * to_local[3]


def _held_copy(held: np.ndarray | None, v: np.ndarray) -> np.ndarray:
    """A copy of v in `held` where it has v's shape and dtype (no allocation from frame to frame), else a new one."""
    if held is None or held.shape != v.shape or held.dtype != v.dtype:
        return np.array(v)
    np.copyto(held, v)
    return held


def _placed(domain: _Domain, pose: Pose) -> tuple[_Domain, np.ndarray, np.ndarray]:
    """Where a rigid frame's pose carries the field's cube, for measuring points from it: (the cube centred where
    the pose puts its centre, the turn and the shift that take points measured from there into the field's local
    coordinates: local = turn @ ((p - centre) * scale) - shift). The centre is snapped to a float32 number where
    that moves it by less than 2^-20 of the side, so float32 points are recentred on the device as the field's
    own are, and the shift carries what the snap moved; else it stays float64 and points are recentred on the host
    (shift 0)."""
    centre = pose.rotation @ domain.centre + pose.translation
    snapped = centre.astype(np.float32).astype(np.float64)
    turn = pose.rotation.T
    if float(np.max(np.abs(snapped - centre))) <= 2.0**-20 * domain.side:
        return (dataclasses.replace(domain, centre=snapped, float32_centre=True), turn,
                turn @ (centre - snapped) * domain.scale)
    return dataclasses.replace(domain, centre=centre, float32_centre=False), turn, np.zeros(3)


def _to_world_units(local: np.ndarray, scale: float) -> None:
    """Divide float32 lengths or offsets by the domain's scale, in place. The scale is a power of two, so the
    result is exact (rounded once where it is subnormal). numpy multiplies float32 by a Python float in
    float32, so a scale float32 cannot hold goes through float64."""
    inverse = 1.0 / scale
    if _float32_holds(inverse):
        local *= np.float32(inverse)
    else:
        local[...] = local.astype(np.float64) * inverse


def _float32_holds(power_of_two: float) -> bool:
    return float(np.finfo(np.float32).tiny) <= power_of_two <= 2.0**127


def _pull_far_points(points: np.ndarray, domain: _Domain):
    """Points more than FAR_POINT domain sides from its centre (whose squared local distances could overflow
    float32 in the kernels, and whose distances to all faces float32 rounds alike) are moved along the line to
    the centre until they are FAR_POINT sides away. For a mesh within r of the centre, a point's distance is the
    moved point's plus the move to within r^2 / (2 FAR_POINT), 3.6e-7 of the side: far below float32's rounding
    of such distances (1/16 of the side at 2^20 sides). The moved point's nearest face is therefore as near as
    any to that rounding, and its closest point is the one reported. Its normal points within r / FAR_POINT
    (8e-7 radians) of the point's own. Returns (all points in local float32 coordinates, (moved rows, their moves
    in world units)), or (None, None) when no point is that far."""
    if len(points) == 0:
        return None, None
    limit = FAR_POINT * domain.local_side
    # first over all coordinates at once: x - c_k <= max - min(c) and c_k - x <= max(c) - min on every axis k. Two
    # reductions of the flat array, where the per-axis bounds below copy the points (0.15 ms of a 65,536-point query
    # on an H100's host, 2026-12-07); a mesh whose centre's coordinates differ by far more than its side goes on
    centre = domain.centre
    if max(float(points.max()) - float(centre.min()), float(centre.max()) - float(points.min())) * domain.scale <= limit / 2.0:
        return None, None
    lo, hi = bounds(points)
    reach = float(np.maximum(np.abs(lo - domain.centre), np.abs(hi - domain.centre)).max())
    if reach * domain.scale <= limit / 2.0:
        # every point within limit / 2 of the centre on every axis, so nearer than limit: nothing to move. Measured
        # from the centre, not the origin, so a mesh far from the origin (1e6 away with a side of 1) does not pay
        # the float64 pass below on every query (1.9 ms for 65,536 points on a 2-core machine, 2026-12-02)
        return None, None
    local = (points.astype(np.float64) - domain.centre) * domain.scale
    radius = np.sqrt(np.einsum("ij,ij->i", local, local))
    rows = np.flatnonzero(radius > limit)
    if len(rows) == 0:
        return None, None
    local[rows] *= (limit / radius[rows])[:, None]
    return np.ascontiguousarray(local, dtype=np.float32), (rows, (radius[rows] - limit) / domain.scale)


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (min, max) of (N, 3) points, in float64 whatever the points' dtype, so the same values give
    the same domain as float32 or float64. numpy reduces axis 0 of an (N, 3) array row by row (2 ms for
    35K points); a transposed copy reduced along its rows takes 0.05 ms."""
    columns = np.ascontiguousarray(points.T)
    return columns.min(axis=1).astype(np.float64), columns.max(axis=1).astype(np.float64)


def _decode_morton(codes: np.ndarray) -> np.ndarray:
    codes = codes.astype(np.int64)
    out = np.zeros((len(codes), 3), dtype=np.float64)
    for bit in range(21):
        for axis in range(3):
            out[:, axis] += ((codes >> (3 * bit + 2 - axis)) & 1) * (1 << bit)
    return out


def _resolve_device(device) -> wp.Device:
    wp.init()
    if device is None:
        return wp.get_device("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    if isinstance(device, wp.Device):
        return device
    if not isinstance(device, str):
        raise InvalidInputError(f"device must be 'cpu', 'cuda' or 'cuda:N' (or None), got {device!r}")
    try:
        resolved = wp.get_device(device)
    except (RuntimeError, ValueError, KeyError) as error:
        raise InvalidInputError(f"device {device!r} is not available here: {error}") from None
    if resolved is None:
        raise InvalidInputError(f"device {device!r} is not available here")
    return resolved
